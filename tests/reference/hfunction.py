"""Chandrasekhar's H-function for isotropic scattering and the plane albedo.

Definitions
-----------
For isotropic scattering with single-scattering albedo ``a`` in (0, 1] the
H-function is the solution of

    H(mu) = 1 + (a/2) mu H(mu) int_0^1 H(mu') / (mu + mu') dmu'.

Using the zeroth-moment identity alpha_0 = int_0^1 H dmu = (2/a)(1 - sqrt(1-a))
this is equivalent to the form that iterates well (Chandrasekhar, Radiative
Transfer, 1960, chapter V):

    1 / H(mu) = sqrt(1 - a) + (a/2) int_0^1 mu' H(mu') / (mu + mu') dmu'.       (*)

Numerical method (``h_function``)
---------------------------------
(*) is discretised on a composite Gauss-Legendre rule: panels [0, 1e-12] and a
geometric sequence of panels from 1e-12 to 1 (ratio about 3), 16 nodes per
panel. The geometric grading resolves both the mu log mu behaviour of H near 0
and the near-singular kernel 1/(mu + mu') for small mu. The discrete system
F_i(x) = x_i (sqrt(1-a) + (a/2) sum_j w_j mu_j x_j / (mu_i + mu_j)) - 1 = 0 is
solved by Newton's method from x = 1 (converges quadratically also for a = 1;
residual < 1e-13). H at an arbitrary mu is obtained by Nystrom interpolation,
i.e. by evaluating the right-hand side of (*) with the nodal values, which is
exact at the nodes and as accurate as the quadrature elsewhere. Accuracy:
better than 1e-10 absolute for mu in [0, 1] (checked against the independent
integral representation below, see tests/workers/test_reference_solutions.py).

Independent representation (``h_function_integral``)
-----------------------------------------------------
For mu >= 0 (Chandrasekhar's explicit solution, chapter V, specialised to
isotropic scattering: characteristic function Psi = a/2, so
1 - 2 int_0^1 Psi(mu) dmu / (1 + mu^2 t^2) = 1 - a arctan(t)/t = 1 - a theta cot theta
with t = tan theta):

    ln H(mu) = -(mu/pi) int_0^{pi/2} ln(1 - a theta cot theta)
                                      / (cos^2 theta + mu^2 sin^2 theta) dtheta,

equivalently, with t = tan theta, -(mu/pi) int_0^inf ln(1 - a arctan(t)/t)
/ (1 + mu^2 t^2) dt. Evaluated with scipy.integrate.quad (slow, ~1e-12).

Plane albedo (``diffuse_reflectance_isotropic_matched``)
-------------------------------------------------------
For a half-space with isotropic scattering and an index-matched boundary
(eta = 1, no Fresnel), illuminated by a collimated beam with direction cosine
mu0 and flux pi F per unit area normal to the beam, the diffusely reflected
intensity is (Chandrasekhar, chapter IV, isotropic scattering function)

    I(mu, mu0) = (a F / 4) mu0 H(mu) H(mu0) / (mu + mu0),

so the reflected flux 2 pi int_0^1 I mu dmu divided by the incident flux
pi F mu0 on the surface is

    R(mu0) = (a/2) H(mu0) int_0^1 mu H(mu) / (mu + mu0) dmu
           = H(mu0) (1/H(mu0) - sqrt(1-a))           by (*)
           = 1 - sqrt(1 - a) H(mu0).

Per unit incident power, dimensionless, all orders of scattering. Checks: a = 1
gives R = 1 (no absorption, nothing transmitted through a half-space); to first
order in a it equals the single-scattering result (a/2)(1 - mu0 ln((1+mu0)/mu0)).
For an anisotropic or mismatched medium there is no such closed form.

Valid range: albedo in (0, 1], mu and mu0 in [0, 1].
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from scipy import integrate

__all__ = [
    "h_function",
    "h_function_integral",
    "h_moment",
    "diffuse_reflectance_isotropic_matched",
]

_PANEL_NODES = 16


@lru_cache(maxsize=4)
def _nodes() -> tuple[np.ndarray, np.ndarray]:
    """Composite Gauss-Legendre nodes and weights on [0, 1], geometrically graded to 0."""
    n_geo = 26  # 1e-12 * 3^k reaches 1 at k ~ 25.2
    bounds = np.concatenate(([0.0], np.geomspace(1e-12, 1.0, n_geo)))
    x, w = np.polynomial.legendre.leggauss(_PANEL_NODES)
    lo, hi = bounds[:-1, None], bounds[1:, None]
    mu = 0.5 * (hi - lo) * x[None, :] + 0.5 * (hi + lo)
    wt = 0.5 * (hi - lo) * w[None, :]
    return mu.ravel(), wt.ravel()


def _check_albedo(albedo: float) -> float:
    a = float(albedo)
    if not (0.0 < a <= 1.0):
        raise ValueError(f"albedo must be in (0, 1], got {albedo}")
    return a


@lru_cache(maxsize=64)
def _nodal_solution(albedo: float) -> np.ndarray:
    """Nodal values H(mu_j) solving the discretised equation (*) by Newton's method."""
    a = _check_albedo(albedo)
    mu, w = _nodes()
    s = math.sqrt(1.0 - a)
    kern = 0.5 * a * (w * mu)[None, :] / (mu[:, None] + mu[None, :])
    x = np.ones_like(mu)
    for _ in range(100):
        kx = kern @ x
        f = x * (s + kx) - 1.0
        jac = np.diag(s + kx) + x[:, None] * kern
        dx = np.linalg.solve(jac, -f)
        x = x + dx
        if np.max(np.abs(dx)) < 1e-15 * np.max(np.abs(x)):
            break
    kx = kern @ x
    res = np.max(np.abs(x * (s + kx) - 1.0))
    if not res < 1e-13:
        raise RuntimeError(f"H-function Newton iteration did not converge (residual {res})")
    return x


def h_function(mu, albedo: float) -> np.ndarray | float:
    """Chandrasekhar's H(mu) for isotropic scattering with single-scattering albedo.

    ``mu``: scalar or array of direction cosines in [0, 1] (dimensionless).
    ``albedo``: sigma_s / sigma_t in (0, 1].
    Returns H(mu) (>= 1), same shape as ``mu``; accurate to about 1e-10.
    """
    a = _check_albedo(albedo)
    m = np.asarray(mu, dtype=np.float64)
    if np.any((m < 0.0) | (m > 1.0)) or np.any(~np.isfinite(m)):
        raise ValueError("mu must be in [0, 1]")
    nodes, w = _nodes()
    x = _nodal_solution(a)
    flat = m.reshape(-1)
    out = np.empty_like(flat)
    # Nystrom interpolation, evaluated in chunks to bound memory.
    for start in range(0, flat.size, 4096):
        mm = flat[start:start + 4096]
        kx = 0.5 * a * ((w * nodes * x)[None, :] / (mm[:, None] + nodes[None, :])).sum(axis=1)
        out[start:start + 4096] = 1.0 / (math.sqrt(1.0 - a) + kx)
    out = out.reshape(m.shape)
    return float(out) if out.ndim == 0 else out


def h_moment(n: int, albedo: float) -> float:
    """n-th moment alpha_n = int_0^1 mu^n H(mu) dmu (alpha_0 = (2/a)(1 - sqrt(1-a)))."""
    a = _check_albedo(albedo)
    mu, w = _nodes()
    return float(np.sum(w * mu**n * _nodal_solution(a)))


def _log_char(theta: float, a: float) -> float:
    """ln(1 - a theta cot theta), with a series for small theta to avoid cancellation."""
    if theta < 0.05:
        t2 = theta * theta
        one_minus = t2 / 3.0 + t2 * t2 / 45.0 + 2.0 * t2**3 / 945.0 + t2**4 / 4725.0
        return math.log((1.0 - a) + a * one_minus)
    if theta >= 0.5 * math.pi:
        return 0.0
    return math.log(1.0 - a * theta / math.tan(theta))


def h_function_integral(mu: float, albedo: float) -> float:
    """H(mu) from the explicit integral representation (independent check; scalar, slow).

    ln H(mu) = -(mu/pi) int_0^{pi/2} ln(1 - a theta cot theta) / (cos^2 + mu^2 sin^2) dtheta.
    """
    a = _check_albedo(albedo)
    mu = float(mu)
    if mu == 0.0:
        return 1.0

    def f(th: float) -> float:
        c, s = math.cos(th), math.sin(th)
        return _log_char(th, a) / (c * c + mu * mu * s * s)

    # The denominator is sharp near theta = pi/2 when mu is small (width ~ mu).
    pts = []
    for k in (0.5, 1.0, 2.0):
        th = 0.5 * math.pi - math.atan(k * mu)
        if 0.0 < th < 0.5 * math.pi:
            pts.append(th)
    val, _ = integrate.quad(f, 0.0, 0.5 * math.pi, points=sorted(pts) or None,
                            epsabs=1e-14, epsrel=1e-12, limit=500)
    return math.exp(-mu / math.pi * val)


def diffuse_reflectance_isotropic_matched(albedo: float, mu0=1.0):
    """Total diffuse reflectance (plane albedo) of an index-matched half-space.

    Isotropic scattering, eta = 1, collimated incidence with direction cosine ``mu0``
    (scalar or array in (0, 1]); all orders of scattering:
    R(mu0) = 1 - sqrt(1 - a) H(mu0). Dimensionless, per unit incident power.
    """
    a = _check_albedo(albedo)
    return 1.0 - math.sqrt(1.0 - a) * h_function(mu0, a)
