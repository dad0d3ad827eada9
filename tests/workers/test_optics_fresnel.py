"""Tests of the interface kernels in workers/walk/optics.py: Fresnel reflectance and refraction.

Deterministic functions are checked against closed forms (normal incidence, Brewster angle,
total internal reflection), identities (energy conservation, reciprocity, Snell's law) and the
independent scalar Fresnel of tests/reference/fresnel.py (closed forms and identities, the vectorised kernel against a scalar one).  No statistical
tests here, so no multiple-testing correction.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tests.reference.fresnel import critical_cosine, fresnel_reflectance, refracted_cosine
from workers.walk.optics import (
    fresnel_dielectric,
    incident_refracted_direction,
    refracted_cos,
)

DTYPES = [torch.float32, torch.float64]


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
    has infinite slope and rounding alone moves it by > 1e-12; those are left out, and so is the
    reverse case, cos_t < 1e-3 (cos_i = 0.8 is exactly critical for eta = 0.6).
    """
    for c in COS_GRID[COS_GRID >= 1e-3]:
        if (1.0 - c * c) / (eta * eta) >= 1.0:
            continue
        ct = refracted_cosine(float(c), eta)
        if ct < 1e-3:
            continue
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
    # cos_t^2 = 1 - sin_t^2 is found to a few ulp of 1 by any float formula, so cos_t itself only to
    # sqrt(eps) at the critical angle (cos_t -> 0): compare squares there, values elsewhere.
    torch.testing.assert_close(ct[ok] ** 2, want**2, rtol=0, atol=1e-15)
    far = want > 1e-3
    torch.testing.assert_close(ct[ok][far], want[far], rtol=0, atol=1e-14)
    assert torch.all((ct >= 0) & (ct <= 1))


def test_refracted_cos_is_exact_at_eta_1():
    """No interface: cos_t = cos_i exactly, however grazing (float32 and float64)."""
    for dtype in (torch.float32, torch.float64):
        c = torch.tensor([0.0, 1e-12, 1e-6, 2e-4, 0.3, 1.0], dtype=dtype)  # c^2 stays a normal float
        assert torch.equal(refracted_cos(c, 1.0), c)
        assert torch.equal(refracted_cos(c, torch.tensor(1.0, dtype=dtype)), c)


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

