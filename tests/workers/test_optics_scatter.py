"""Tests of scatter_direction in workers/walk/optics.py: rotating a direction by (cos theta, phi).

Unit length and the cosine to the incoming direction are checked on random directions, the poles
and both sides of the |uz| switch to the polar frame; the azimuth about the incoming direction is
chi-square tested for uniformity (tests/support/stats.py); and the result is compared with a plain-Python
rotation through frame-independent invariants (a chi-square test of every sampler against its own pdf, closed forms, and the vectorised kernel against a scalar one).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tests.support.stats import assert_chi2
from workers.walk.optics import scatter_direction

DTYPES = [torch.float32, torch.float64]

# Chi-square tests of the azimuth family (Sidak correction in tests.support.stats): every one is in
# test_scatter_direction_azimuth_uniform, the only statistical test of this module.
N_AZIMUTH_CHI2 = 4 * 2 * 2  # direction sets x cos_theta x directions per set


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
