"""Tests of the sampling kernels in workers/walk/optics.py: Henyey-Greenstein phase function and
exponential free path.

Samplers are chi-square tested against their own pdf with cell masses integrated by scipy
(tests/support/stats.py), pdfs against closed forms and quadrature (chi-square against its own pdf, identities, the vectorised kernel against a scalar one).  Uniforms for
the samplers come from numpy's PCG64 so that these tests do not depend on workers/walk/rng.py.
Fresnel and refraction are in tests/workers/test_optics_fresnel.py, scatter_direction in
tests/workers/test_optics_scatter.py.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
import torch
from scipy import integrate

from tests.reference.single_scattering import hg_phase
from tests.support.stats import assert_chi2, assert_mean, assert_samples_match_pdf, cell_masses, chi2_test, histogram
from workers.walk.optics import (
    exponential_pdf,
    hg_pdf,
    sample_exponential,
    sample_hg,
)

DTYPES = [torch.float32, torch.float64]
G_VALUES = [-0.9, -0.5, 0.0, 1e-4, 0.3, 0.7, 0.9, 0.99]
G_EXTREME = [-0.999, -0.99, -0.9, -0.5, -1e-4, 0.0, 1e-8, 1e-4, 0.3, 0.7, 0.9, 0.99, 0.999]
N_SAMPLES = 1_000_000

# Chi-square tests per family (Sidak correction in tests.support.stats).  Each count is the number of
# assert_chi2 / assert_samples_match_pdf calls of one family, all of which are in this module:
# test_sample_hg_chi2 (one per g x dtype) and test_sample_exponential_chi2_and_mean (one per
# dtype).  The azimuth family went to tests/workers/test_optics_scatter.py with its own count.
N_HG_CHI2 = len(G_VALUES) * len(DTYPES)
N_EXP_CHI2 = len(DTYPES)


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

