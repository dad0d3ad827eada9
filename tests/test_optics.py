"""Tests of the physics kernels in workers/optics.py.

Samplers are chi-square tested against their own pdf with cell masses integrated by scipy
(tests/stats.py), deterministic functions against closed forms, identities and the independent
scalar Fresnel of tests/reference/fresnel.py, and scatter_direction against a plain-Python
rotation (STYLE.md points 7-9).  Uniforms for the samplers come from numpy's PCG64 so that these
tests do not depend on workers/rng.py.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
import torch
from scipy import integrate

from tests.reference.fresnel import critical_cosine, fresnel_reflectance, refracted_cosine
from tests.reference.single_scattering import hg_phase
from tests.stats import assert_chi2, assert_mean, assert_samples_match_pdf, cell_masses, chi2_test, histogram
from workers.optics import (
    exponential_pdf,
    fresnel_dielectric,
    hg_pdf,
    incident_refracted_direction,
    refracted_cos,
    sample_exponential,
    sample_hg,
    scatter_direction,
)

DTYPES = [torch.float32, torch.float64]
G_VALUES = [-0.9, -0.5, 0.0, 1e-4, 0.3, 0.7, 0.9, 0.99]
G_EXTREME = [-0.999, -0.99, -0.9, -0.5, -1e-4, 0.0, 1e-8, 1e-4, 0.3, 0.7, 0.9, 0.99, 0.999]
N_SAMPLES = 1_000_000

# Chi-square tests per family (Sidak correction in tests.stats).
N_HG_CHI2 = len(G_VALUES) * len(DTYPES)
N_EXP_CHI2 = len(DTYPES)
N_AZIMUTH_CHI2 = 4 * 2 * 2  # direction sets x cos_theta x directions per set


def _uniforms(n: int, dtype: torch.dtype, seed: int) -> torch.Tensor:
    """n uniforms in [0, 1): 53-bit for float64, the 24-bit float32 grid for float32."""
    rng = np.random.default_rng(seed)
    if dtype == torch.float32:
        return torch.from_numpy(rng.random(n, dtype=np.float32))
    return torch.from_numpy(rng.random(n))


# --- Henyey-Greenstein -----------------------------------------------------------------------------


def _hg_cos_pdf(g: float):
    """pdf of cos(theta) under HG, 2 pi p(cos), evaluated by the kernel in float64."""

    def pdf(c: float) -> float:
        return 2.0 * math.pi * float(hg_pdf(torch.tensor(c, dtype=torch.float64), g))

    return pdf


def _cos_edges() -> np.ndarray:
    """Cells in cos(theta): 100 uniform cells refined geometrically towards both poles, where
    HG with |g| near 1 concentrates its mass (down to cells of 1e-5, far above float32 ulps)."""
    near = np.geomspace(1e-5, 2e-2, 30)
    return np.unique(np.concatenate([np.linspace(-1.0, 1.0, 101), -1.0 + near, 1.0 - near]))


@functools.lru_cache(maxsize=None)
def _hg_masses(g: float) -> np.ndarray:
    """Expected mass per cell of _cos_edges(), by quadrature of hg_pdf (independent of sample_hg)."""
    return cell_masses(_hg_cos_pdf(g), _cos_edges())


def _quad_sphere(f, g: float) -> float:
    """Integral of f(cos) over the sphere, 2 pi int_{-1}^{1} f dcos, with the HG peak resolved."""
    peak = [s * (1.0 - 10.0**-k) for s in (-1.0, 1.0) for k in range(1, 7)]
    val, _ = integrate.quad(lambda c: 2.0 * math.pi * f(c), -1.0, 1.0, points=peak, limit=500, epsabs=1e-14, epsrel=1e-13)
    return val


@pytest.mark.parametrize("g", G_EXTREME)
def test_hg_pdf_normalised_with_mean_cosine_g(g):
    p = lambda c: float(hg_pdf(torch.tensor(c, dtype=torch.float64), g))  # noqa: E731
    assert _quad_sphere(p, g) == pytest.approx(1.0, abs=1e-9)
    assert _quad_sphere(lambda c: c * p(c), g) == pytest.approx(g, abs=1e-9)
    # Second Legendre moment of HG is g^2: E[cos^2] = (1 + 2 g^2) / 3.
    assert _quad_sphere(lambda c: c * c * p(c), g) == pytest.approx((1.0 + 2.0 * g * g) / 3.0, abs=1e-9)


@pytest.mark.parametrize("dtype", DTYPES)
def test_hg_pdf_matches_formula_and_broadcasts(dtype):
    c = torch.linspace(-1.0, 1.0, 201, dtype=torch.float64)
    g = torch.tensor([-0.9, 0.0, 0.5, 0.99], dtype=torch.float64).unsqueeze(1)
    got = hg_pdf(c.to(dtype), g.to(dtype))
    assert got.shape == (4, 201) and got.dtype == dtype
    want = np.stack([hg_phase(c.numpy(), float(gi)) for gi in g.flatten()])
    if dtype == torch.float64:
        rtol = np.full((4, 1), 1e-12)
    else:
        # 1 + g^2 - 2 g cos cancels near the forward peak: its float32 rounding (~1e-7 absolute)
        # is relative to (1 - |g|)^2, and the pdf takes its 3/2 power.
        gg = np.abs(g.numpy())
        rtol = 2e-6 + 2e-7 * (1.0 + gg * gg) / (1.0 - gg) ** 2
    np.testing.assert_array_less(np.abs(got.double().numpy() - want), rtol * want)
    # Isotropic at g = 0: 1 / (4 pi) everywhere.
    np.testing.assert_allclose(hg_pdf(c.to(dtype), 0.0).double().numpy(), 1.0 / (4.0 * math.pi), rtol=2e-7)


@pytest.mark.parametrize("dtype", DTYPES, ids=["f32", "f64"])
@pytest.mark.parametrize("g", G_VALUES)
def test_sample_hg_chi2(g, dtype):
    u = _uniforms(N_SAMPLES, dtype, seed=1000 + G_VALUES.index(g))
    cos = sample_hg(u, g)
    assert cos.dtype == dtype
    counts = histogram(cos.numpy(), _cos_edges())
    assert_chi2(counts, _hg_masses(g), N_SAMPLES, n_tests=N_HG_CHI2, what=f"sample_hg g={g} {dtype}")


@pytest.mark.parametrize("g", G_VALUES)
def test_sample_hg_moments(g):
    """Sample mean of cos is g, of cos^2 is (1 + 2 g^2)/3, within 4 standard errors (closed-form
    variances from the Legendre moments g^l of HG)."""
    cos = sample_hg(_uniforms(N_SAMPLES, torch.float64, seed=2000 + G_VALUES.index(g)), g).numpy()
    m2 = (1.0 + 2.0 * g * g) / 3.0
    m4 = (8.0 * g**4 + 30.0 * m2 - 3.0) / 35.0  # from E[P4(cos)] = g^4
    assert_mean(cos, g, std=math.sqrt(m2 - g * g), what=f"mean cos, g={g}")
    assert_mean(cos * cos, m2, std=math.sqrt(m4 - m2 * m2), what=f"mean cos^2, g={g}")


def test_chi2_rejects_wrong_samplers():
    """The test has power: a slightly wrong g, and the sign typo of the classic inversion formula
    (which samples HG with -g), are both rejected decisively."""
    u = _uniforms(N_SAMPLES, torch.float64, seed=7)
    near_miss = histogram(sample_hg(u, 0.68).numpy(), _cos_edges())
    assert not chi2_test(near_miss, _hg_masses(0.7), N_SAMPLES).passed
    g = 0.3
    s = (1.0 - g * g) / (1.0 - g + 2.0 * g * u)
    typo = -(1.0 + g * g - s * s) / (2.0 * abs(g))
    assert not chi2_test(histogram(typo.numpy(), _cos_edges()), _hg_masses(g), N_SAMPLES).passed


def _edge_uniforms(dtype: torch.dtype) -> torch.Tensor:
    tiny = [0.0, 2.0**-24, 2.0**-20, 1e-7]
    if dtype == torch.float64:
        tiny += [1e-300, 1e-16, 1e-12]
    vals = tiny + [1.0 - t for t in tiny] + [0.5]
    return torch.tensor(sorted(set(vals)), dtype=dtype)


@pytest.mark.parametrize("dtype", DTYPES, ids=["f32", "f64"])
@pytest.mark.parametrize("g", G_EXTREME)
def test_sample_hg_finite_at_extreme_u_and_g(g, dtype):
    u = _edge_uniforms(dtype)
    cos = sample_hg(u, g)
    assert torch.isfinite(cos).all(), cos
    assert (cos >= -1.0).all() and (cos <= 1.0).all()
    # u = 0 and u = 1 map to the poles (docstring); float32 allows a few ulp of |g| near 1.
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    assert float(cos[0]) == pytest.approx(-1.0, abs=tol)
    assert float(cos[-1]) == pytest.approx(1.0, abs=tol)
    # The pdf at the sampled values is finite and positive (no clamp artefacts).
    p = hg_pdf(cos, g)
    assert torch.isfinite(p).all() and (p > 0).all()


# Largest backward step allowed in float32 (a few ulp of values near 1, 2**-24 ~ 6e-8).
F32_MONOTONE_SLACK = 1e-6


@pytest.mark.parametrize("dtype", DTYPES, ids=["f32", "f64"])
@pytest.mark.parametrize("g", G_EXTREME)
def test_sample_hg_monotone_in_u(g, dtype):
    """An inverse CDF is non-decreasing in u; float32 may only wobble by rounding."""
    u = torch.linspace(0.0, 1.0, 2**20 + 1, dtype=torch.float64).to(dtype)
    cos = sample_hg(u, g)
    step = torch.diff(cos)
    slack = 0.0 if dtype == torch.float64 else F32_MONOTONE_SLACK
    k = int(torch.argmin(step))
    assert float(step[k]) >= -slack, (
        f"sample_hg decreases by {-float(step[k]):.3g} between u = {float(u[k])!r} and {float(u[k + 1])!r} "
        f"(cos {float(cos[k])!r} -> {float(cos[k + 1])!r}), g = {g}, {dtype}"
    )


@pytest.mark.parametrize("g", G_EXTREME)
def test_sample_hg_float32_accuracy(g):
    """float32 sample_hg agrees with the float64 one on the same (float32) uniforms.

    A 1e-5 error in cos is far above float32 rounding (~1e-7) yet small for the walk.
    """
    u32 = torch.linspace(0.0, 1.0, 2**20 + 1, dtype=torch.float64).float()
    ref = sample_hg(u32.double(), g)
    err = (sample_hg(u32, g).double() - ref).abs()
    k = int(torch.argmax(err))
    assert float(err[k]) <= 1e-5, (
        f"float32 sample_hg(u={float(u32[k])!r}, g={g}) = {float(sample_hg(u32[k:k + 1], g)[0])!r}, "
        f"float64 gives {float(ref[k])!r}"
    )


def test_sample_hg_tensor_g_broadcasts():
    u = torch.tensor([0.1, 0.5, 0.9], dtype=torch.float64)
    g = torch.tensor([[-0.5], [0.0], [0.8]], dtype=torch.float64)
    got = sample_hg(u, g)
    for i, gi in enumerate(g.flatten().tolist()):
        torch.testing.assert_close(got[i], sample_hg(u, gi), rtol=0, atol=1e-15)


# --- exponential free path -------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", DTYPES, ids=["f32", "f64"])
def test_sample_exponential_chi2_and_mean(dtype):
    # u in (0, 1]: 1 - [0, 1) excludes 0 as the kernel requires.
    u = 1.0 - _uniforms(N_SAMPLES, dtype, seed=3000 + DTYPES.index(dtype))
    s = sample_exponential(u)
    assert s.dtype == dtype and torch.isfinite(s).all() and (s >= 0).all()
    pdf = lambda x: float(exponential_pdf(torch.tensor(x, dtype=torch.float64)))  # noqa: E731
    edges = np.concatenate([np.linspace(0.0, 4.0, 81), np.linspace(4.25, 14.0, 40)])
    assert_samples_match_pdf(s.numpy(), pdf, edges, n_tests=N_EXP_CHI2, what=f"sample_exponential {dtype}")
    assert_mean(s.numpy(), 1.0, std=1.0, what="mean free path")


def test_exponential_pdf_closed_form():
    s = torch.tensor([-1.0, -1e-12, 0.0, 0.5, 3.0, 50.0], dtype=torch.float64)
    want = torch.tensor([0.0, 0.0, 1.0, math.exp(-0.5), math.exp(-3.0), math.exp(-50.0)], dtype=torch.float64)
    torch.testing.assert_close(exponential_pdf(s), want, rtol=1e-15, atol=0)
    total, _ = integrate.quad(lambda x: float(exponential_pdf(torch.tensor(x, dtype=torch.float64))), 0, math.inf)
    assert total == pytest.approx(1.0, abs=1e-10)


def test_sample_exponential_inverse_cdf():
    u = torch.tensor([1.0, 0.5, math.exp(-2.0), 2.0**-24], dtype=torch.float64)
    torch.testing.assert_close(sample_exponential(u), torch.tensor([0.0, math.log(2.0), 2.0, 24 * math.log(2.0)],
                                                                   dtype=torch.float64), rtol=1e-15, atol=0)


# --- Fresnel ---------------------------------------------------------------------------------------

ETAS = [0.5, 0.6, 1 / 1.5, 0.75, 0.9, 1.0, 1.1, 1.33, 1.4, 1.5, 1.8, 2.0, 2.5]
COS_GRID = np.concatenate([[0.0, 1e-12, 1e-6, 1e-3], np.linspace(0.01, 0.99, 99), [1.0 - 1e-9, 1.0]])


def _fr(cos, eta, dtype=torch.float64) -> np.ndarray:
    return fresnel_dielectric(torch.as_tensor(np.asarray(cos), dtype=dtype), eta).double().numpy()


@pytest.mark.parametrize("eta", [1.5, 1.33, 2.0, 0.5, 1 / 1.5, 1.0])
def test_fresnel_normal_incidence(eta):
    want = ((eta - 1.0) / (eta + 1.0)) ** 2
    assert _fr([1.0], eta)[0] == pytest.approx(want, abs=1e-15)
    if eta == 1.5:
        assert _fr([1.0], eta)[0] == pytest.approx(0.04, abs=1e-15)


@pytest.mark.parametrize("eta", [0.5, 1 / 1.5, 1 / 1.33, 0.9])
def test_fresnel_total_internal_reflection(eta):
    cos_c = math.sqrt(1.0 - eta * eta)  # critical cosine of incidence for eta < 1
    below = np.linspace(0.0, cos_c * (1 - 1e-9), 50)
    np.testing.assert_array_equal(_fr(below, eta), 1.0)
    above = np.linspace(cos_c * (1 + 1e-6), 1.0, 50)
    r = _fr(above, eta)
    assert np.all(r < 1.0)
    # Continuous at the critical angle: R -> 1 from above.
    assert _fr([cos_c * (1 + 1e-12)], eta)[0] == pytest.approx(1.0, abs=1e-4)


@pytest.mark.parametrize("eta", [0.6, 1 / 1.33, 1.33, 1.5, 2.4])
def test_fresnel_brewster_angle(eta):
    """At tan(theta_B) = eta, r_p = 0 and r_s = (1 - eta^2)/(1 + eta^2) (theta_i + theta_t = 90 deg)."""
    cos_b = 1.0 / math.sqrt(1.0 + eta * eta)
    rs = (1.0 - eta * eta) / (1.0 + eta * eta)
    assert _fr([cos_b], eta)[0] == pytest.approx(0.5 * rs * rs, rel=1e-12)


@pytest.mark.parametrize("eta", ETAS)
def test_fresnel_matches_reference(eta):
    got = _fr(COS_GRID, eta)
    want = np.array([fresnel_reflectance(float(c), eta) for c in COS_GRID])
    # eta = 1 below cos ~ 1e-3 is checked against the physics (R = 0) in the next test; the
    # reference, like any formula through 1 - cos^2, degrades there.
    ok = (COS_GRID >= 1e-3) if eta == 1.0 else slice(None)
    np.testing.assert_allclose(got[ok], want[ok], rtol=0, atol=1e-13)


@pytest.mark.parametrize("dtype", DTYPES, ids=["f32", "f64"])
def test_fresnel_index_matched_reflects_nothing(dtype):
    """eta = 1: there is no interface, R = 0 at every cos > 0 (the docstring says so too).

    Computing cos_t from 1 - (1 - cos_i^2)/eta^2 loses cos_i^2 to rounding at grazing angles:
    R grows to ~1e-5 at cos_i = 1e-3 in float32 and jumps to 1 ("TIR") once cos_i^2 is below
    the rounding of 1 (cos_i < ~2.4e-4 in float32, < ~1e-8 in float64).
    """
    cos = COS_GRID[COS_GRID > 0]
    if dtype == torch.float32:
        cos = cos[cos >= 1e-6]  # smallest grid values are below float32 resolution of 1 - cos^2 anyway
    r = _fr(cos, 1.0, dtype)
    tol = 1e-12 if dtype == torch.float64 else 1e-6
    k = int(np.argmax(r))
    assert r[k] <= tol, f"fresnel_dielectric(cos_i={cos[k]!r}, eta=1.0) = {r[k]!r} in {dtype}, expected 0"


@pytest.mark.parametrize("eta", [e for e in ETAS if e != 1.0])
def test_fresnel_float32_matches_reference(eta):
    """float32 against the float64 reference at the same (float32-rounded) cosines.

    Near the critical angle R has infinite slope in cos_t = sqrt(1 - sin_t^2), and float32
    rounding of 1 - sin_t^2 (~1e-7) moves R by ~sqrt(1e-7); those points are left out.
    """
    c32 = COS_GRID.astype(np.float32).astype(np.float64)
    sin2_t = (1.0 - c32 * c32) / (eta * eta)
    ok = (np.abs(1.0 - sin2_t) > 1e-3) & (c32 >= 1e-3)
    got = _fr(c32[ok], eta, torch.float32)
    want = np.array([fresnel_reflectance(float(c), eta) for c in c32[ok]])
    np.testing.assert_allclose(got, want, rtol=0, atol=2e-6)


@pytest.mark.parametrize("eta", [e for e in ETAS if e != 1.0])
def test_fresnel_grazing_is_total(eta):
    assert _fr([0.0], eta)[0] == 1.0


@pytest.mark.parametrize("eta", ETAS)
def test_fresnel_energy_conservation(eta):
    """R + T = 1 with T from the transmitted power of the amplitude coefficients:
    T = (eta cos_t / cos_i) (t_s^2 + t_p^2) / 2, t_s = 2 cos_i / (cos_i + eta cos_t),
    t_p = 2 cos_i / (eta cos_i + cos_t)."""
    for c in COS_GRID[COS_GRID > 0]:
        # At eta = 1 cos_t = c exactly (1 - sin^2 loses it at grazing incidence, which would make
        # this reference T, not R, inaccurate); elsewhere the usual form, which decides total
        # internal reflection at the exact critical angle (a grid point for eta 0.6) the same way.
        cos2_t = c * c if eta == 1.0 else 1.0 - (1.0 - c * c) / (eta * eta)
        if cos2_t <= 0.0:
            continue
        ct = math.sqrt(cos2_t)
        ts = 2.0 * c / (c + eta * ct)
        tp = 2.0 * c / (eta * c + ct)
        t = (eta * ct / c) * 0.5 * (ts * ts + tp * tp)
        assert _fr([c], eta)[0] + t == pytest.approx(1.0, abs=1e-12), (c, eta)


@pytest.mark.parametrize("eta", ETAS)
def test_fresnel_reciprocity(eta):
    """R(cos_i, eta) = R(cos_t, 1/eta): the same interface crossed backwards.

    Grazing cos_i (< 1e-3) maps to cos_t at the critical angle of the reverse crossing, where R
    has infinite slope and rounding alone moves it by > 1e-12; those are left out.
    """
    for c in COS_GRID[COS_GRID >= 1e-3]:
        if (1.0 - c * c) / (eta * eta) >= 1.0:
            continue
        ct = refracted_cosine(float(c), eta)
        assert _fr([c], eta)[0] == pytest.approx(_fr([ct], 1.0 / eta)[0], abs=1e-12), (c, eta)


def test_fresnel_tensor_eta_and_inputs_unchanged():
    cos = torch.tensor([0.2, 0.7, 1.0], dtype=torch.float64)
    eta = torch.tensor([[0.7], [1.0], [1.5]], dtype=torch.float64)
    before = cos.clone()
    got = fresnel_dielectric(cos, eta)
    assert got.shape == (3, 3) and torch.equal(cos, before)
    for i, e in enumerate(eta.flatten().tolist()):
        torch.testing.assert_close(got[i], fresnel_dielectric(cos, e), rtol=0, atol=1e-15)


# --- refraction ------------------------------------------------------------------------------------


@pytest.mark.parametrize("eta", ETAS)
def test_refracted_cos_snell(eta):
    c = torch.as_tensor(COS_GRID, dtype=torch.float64)
    ct = refracted_cos(c, eta)
    sin_i = torch.sqrt(1.0 - c * c)
    tir = sin_i > eta
    assert torch.all(ct[tir] == 0.0)
    ok = ~tir
    torch.testing.assert_close(eta * torch.sqrt(1.0 - ct[ok] ** 2), sin_i[ok], rtol=0, atol=1e-7)
    want = torch.tensor([refracted_cosine(float(x), eta) for x in c[ok]], dtype=torch.float64)
    torch.testing.assert_close(ct[ok], want, rtol=0, atol=1e-14)
    assert torch.all((ct >= 0) & (ct <= 1))


@pytest.mark.parametrize("eta", [0.6, 0.75, 1.0, 1.33, 1.5, 2.5])
def test_incident_refracted_direction(eta):
    limit = math.asin(min(1.0, eta))
    # 1e-6 short of the limit: closer, sin(theta) rounds to sin(limit) in float64.
    for theta in np.linspace(0.0, limit * (1 - 1e-6), 25):
        d = incident_refracted_direction(float(theta), eta)
        assert math.hypot(*d) == pytest.approx(1.0, abs=1e-14)
        assert d[1] == 0.0 and d[2] < 0.0 and d[0] >= 0.0
        assert eta * d[0] == pytest.approx(math.sin(theta), abs=1e-14)  # Snell
        # Compare cos_t^2: cos_t itself is ill-conditioned near the critical angle.
        assert d[2] ** 2 == pytest.approx(refracted_cosine(math.cos(theta), eta) ** 2, abs=1e-14)
    assert incident_refracted_direction(0.0, eta) == (0.0, 0.0, -1.0)


@pytest.mark.parametrize("eta", [0.5, 1 / 1.33, 0.9])
def test_incident_refracted_direction_beyond_critical_raises(eta):
    theta_c = math.asin(eta)
    for theta in (theta_c * (1 + 1e-6), 0.5 * (theta_c + math.pi / 2), math.pi / 2):
        with pytest.raises(ValueError):
            incident_refracted_direction(theta, eta)
    assert critical_cosine(1.0 / eta) == pytest.approx(math.cos(theta_c), abs=1e-12)


# --- scatter_direction -----------------------------------------------------------------------------

SWITCH = 0.99999  # |uz| above which scatter_direction uses its polar frame


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _direction_sets() -> dict[str, np.ndarray]:
    """Unit directions (float64, [n, 3]) by category."""
    rng = np.random.default_rng(11)
    out = {"random": _unit(rng.normal(size=(2000, 3)))}
    out["poles"] = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
    rows = {"below_switch": [], "above_switch": []}
    for sign in (1.0, -1.0):
        for name, uzs in (
            ("below_switch", [SWITCH - 1e-6, SWITCH - 1e-7, 0.9999]),
            ("above_switch", [SWITCH + 1e-7, SWITCH + 1e-6, 0.999995, 1 - 1e-8]),
        ):
            for uz in uzs:
                for a in (0.0, 1.0, 2.5, 4.0):
                    s = math.sqrt(1.0 - uz * uz)
                    rows[name].append([s * math.cos(a), s * math.sin(a), sign * uz])
    out.update({k: np.array(v) for k, v in rows.items()})
    return out


DIRECTIONS = _direction_sets()


def _call_scatter(u: np.ndarray, cos_t: np.ndarray, phi: np.ndarray, dtype) -> np.ndarray:
    t = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=dtype)  # noqa: E731
    if dtype == torch.float32:
        # Renormalise in float32 so the input is a unit vector at that precision.
        u = t(u)
        u = u / torch.linalg.vector_norm(u, dim=-1, keepdim=True)
    else:
        u = t(u)
    ux, uy, uz = u[:, 0], u[:, 1], u[:, 2]
    nx, ny, nz = scatter_direction(ux, uy, uz, t(cos_t), t(phi))
    return torch.stack([nx, ny, nz], dim=-1).double().numpy(), u.double().numpy()


@pytest.mark.parametrize("dtype", DTYPES, ids=["f32", "f64"])
@pytest.mark.parametrize("which", ["random", "poles", "below_switch", "above_switch"])
def test_scatter_direction_unit_and_cosine(which, dtype):
    base = DIRECTIONS[which]
    rng = np.random.default_rng(12)
    reps = max(1, 4000 // len(base))
    u = np.repeat(base, reps, axis=0)
    cos_t = rng.uniform(-1.0, 1.0, len(u))
    cos_t[:3] = [-1.0, 0.0, 1.0]
    phi = rng.uniform(0.0, 2 * math.pi, len(u))
    v, u_used = _call_scatter(u, cos_t, phi, dtype)
    tol = 1e-12 if dtype == torch.float64 else 1e-6
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1.0, rtol=0, atol=tol)
    dot = np.sum(u_used * v, axis=1)
    k = int(np.argmax(np.abs(dot - cos_t)))
    assert abs(dot[k] - cos_t[k]) <= tol, (
        f"u . u' = {dot[k]!r} but cos_theta = {cos_t[k]!r} for u = {u_used[k].tolist()}, phi = {phi[k]!r} ({dtype})"
    )


def _frame(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A right-handed orthonormal frame (e1, e2) perpendicular to unit u (plain numpy)."""
    a = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = a - np.dot(a, u) * u
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(u, e1)


@pytest.mark.parametrize("cos_t", [0.3, -0.8])
@pytest.mark.parametrize("which", ["random", "poles", "below_switch", "above_switch"])
def test_scatter_direction_azimuth_uniform(which, cos_t):
    """For phi uniform, the azimuth of u' about u (in a frame of our own) is uniform: chi-square."""
    n = 2**15
    rng = np.random.default_rng(13)
    picks = DIRECTIONS[which][rng.choice(len(DIRECTIONS[which]), 2, replace=False)]
    for u0 in picks:
        phi = rng.uniform(0.0, 2 * math.pi, n)
        v, _ = _call_scatter(np.tile(u0, (n, 1)), np.full(n, cos_t), phi, torch.float64)
        e1, e2 = _frame(u0)
        psi = np.mod(np.arctan2(v @ e2, v @ e1), 2 * math.pi)
        cells = 32
        counts = np.bincount(np.minimum((psi * cells / (2 * math.pi)).astype(int), cells - 1), minlength=cells)
        assert_chi2(counts, np.full(cells, 1.0 / cells), n, n_tests=N_AZIMUTH_CHI2, what=f"azimuth about {u0}")


def _scatter_scalar(u, cos_t: float, phi: float) -> list[float]:
    """Plain-Python rotation: u' = cos_t u + sin_t (cos phi e1 + sin phi e2), frame built around u."""
    ux, uy, uz = u
    a = (1.0, 0.0, 0.0) if abs(ux) < 0.9 else (0.0, 1.0, 0.0)
    d = a[0] * ux + a[1] * uy + a[2] * uz
    e1 = [a[0] - d * ux, a[1] - d * uy, a[2] - d * uz]
    n1 = math.sqrt(sum(x * x for x in e1))
    e1 = [x / n1 for x in e1]
    e2 = [uy * e1[2] - uz * e1[1], uz * e1[0] - ux * e1[2], ux * e1[1] - uy * e1[0]]
    sin_t = math.sqrt(max(0.0, 1.0 - cos_t * cos_t))
    return [cos_t * ui + sin_t * (math.cos(phi) * a1 + math.sin(phi) * a2) for ui, a1, a2 in zip(u, e1, e2)]


def _invariants(u, v1, v2) -> tuple[float, float, float]:
    """(u . v1, u . v2, unsigned angle between the parts of v1 and v2 perpendicular to u)."""
    u, v1, v2 = (np.asarray(x, dtype=np.float64) for x in (u, v1, v2))
    p1 = v1 - np.dot(u, v1) * u
    p2 = v2 - np.dot(u, v2) * u
    ang = math.atan2(np.linalg.norm(np.cross(p1, p2)), np.dot(p1, p2))
    return float(np.dot(u, v1)), float(np.dot(u, v2)), ang


@pytest.mark.parametrize("which", ["random", "poles", "below_switch", "above_switch"])
def test_scatter_direction_matches_scalar_rotation(which):
    """Vectorized vs plain scalar on a handful of photons.  The azimuth origins differ between
    frames, so compare invariants: the cosines to u and the angle between two rotations by
    phi1 and phi2, which must be |phi2 - phi1| (mod 2 pi, folded into [0, pi])."""
    rng = np.random.default_rng(14)
    base = DIRECTIONS[which]
    us = base[rng.choice(len(base), size=min(8, len(base)), replace=False)]
    for u in us:
        for cos_t in (0.9, 0.1, -0.6):
            phi1, phi2 = rng.uniform(0, 2 * math.pi, 2)
            got, _ = _call_scatter(np.array([u, u]), np.array([cos_t, cos_t]), np.array([phi1, phi2]), torch.float64)
            ref = [_scatter_scalar(tuple(u), cos_t, p) for p in (phi1, phi2)]
            d = abs(phi2 - phi1) % (2 * math.pi)
            want_angle = min(d, 2 * math.pi - d)
            inv_got = _invariants(u, got[0], got[1])
            inv_ref = _invariants(u, ref[0], ref[1])
            np.testing.assert_allclose(inv_ref, (cos_t, cos_t, want_angle), rtol=0, atol=1e-12)
            np.testing.assert_allclose(inv_got, inv_ref, rtol=0, atol=1e-9, err_msg=f"u = {u.tolist()}, cos_t = {cos_t}")
