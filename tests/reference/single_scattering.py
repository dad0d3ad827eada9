"""Exact single-scattering reflectance of a semi-infinite HG medium, by quadrature.

Geometry and conventions (workers/walk/conventions.py): medium z < 0, surface z = 0, outward
normal +z, outside index 1, relative index ``eta``. The incoming ray travels along
(sin ti, 0, -cos ti) and hits the origin; it refracts into d0 = (sin tt, 0, -mu_t)
with sin tt = sin ti / eta, and carries the power 1 - Fr(cos ti, eta). Extinction
``sigma_t`` (1/mm), albedo a = sigma_s / sigma_t, Henyey-Greenstein phase function

    p(cos) = (1 - g^2) / (4 pi (1 + g^2 - 2 g cos)^{3/2})    (per steradian).

A path leaves after exactly one scattering event ("single" component) when: the
first collision happens at path length s (density sigma_t exp(-sigma_t s)), i.e.
at depth z = s mu_t; the photon scatters (probability a) into direction w with
density p(d0 . w); w points up (w_z = mu > 0); it reaches the surface without a
further collision (probability exp(-sigma_t z / mu)); and it is transmitted with
T(mu) = 1 - Fr(mu, 1/eta), which is 0 under total internal reflection
(mu < mu_c = sqrt(1 - 1/eta^2) for eta > 1).

(a) Total single-scattering reflectance. The s-integral is elementary:

    int_0^inf sigma_t e^{-sigma_t s} e^{-sigma_t s mu_t / mu} ds = mu / (mu + mu_t),

so
    Rd_single = (1 - Fr_i) a int_{mu > 0} p(d0 . w) mu / (mu + mu_t) T(mu) dw.

It does not depend on sigma_t (scale invariance). With w = (sin th cos phi,
sin th sin phi, mu), d0 . w = sin tt sin th cos phi - mu_t mu, the azimuthal
integral of the HG phase function is closed form: writing the HG denominator as
c - d cos phi with c = 1 + g^2 + 2 g mu_t mu and d = 2 |g| sin tt sin th,

    int_0^{2 pi} (c - d cos phi)^{-3/2} dphi = 4 E(m) / ((c - d) sqrt(c + d)),
    m = 2 d / (c + d),

(E the complete elliptic integral of the second kind with parameter m; at
d = 0 this is 2 pi c^{-3/2}), which leaves a 1-D quadrature over mu in
[mu_c, 1] done with adaptive Gauss-Kronrod (scipy quad) with break points
at the phase-function peak. For eta = 1, g = 0, normal incidence:
Rd_single = (a/2) int_0^1 mu/(mu+1) dmu = a (1 - ln 2) / 2.

(b) Radial profile at normal incidence (d0 = -z, mu_t = 1). The scattering point
is on the axis at depth z, and a photon leaving upward with cosine mu exits at
radius r = z tan th = z sqrt(1 - mu^2) / mu. The exit radius lies in [r_lo, r_hi)
iff z is in [r_lo mu / sqrt(1-mu^2), r_hi mu / sqrt(1-mu^2)). Integrating
sigma_t e^{-sigma_t z} e^{-sigma_t z / mu} over that z-range in closed form,

    G(r_lo, r_hi) = C(r_lo) - C(r_hi),
    C(r) = (1 - Fr_0) a int_{mu_c}^1 2 pi p(-mu) T(mu) mu / (1 + mu)
                              exp(-sigma_t r u(mu)) dmu,
    u(mu) = (1 + mu) / sqrt(1 - mu^2) = sqrt((1 + mu) / (1 - mu)),

since sigma_t (1 + 1/mu) * r mu / sqrt(1 - mu^2) = sigma_t r u(mu). C(0) is
Rd_single of (a) at normal incidence, so the annuli of [0, inf) sum to it.
G is the fraction of incident power (dimensionless) leaving through the
annulus; the radial reflectance is Rd(r) = G / (pi (r_hi^2 - r_lo^2)) in 1/mm^2.
C(r) is evaluated for all edges at once with scipy.integrate.quad_vec
(adaptive, vector valued), absolute accuracy about 1e-11.

(c) Radial and directional profile at normal incidence. The exit direction is
radial (phi_o = 0) and its outside cosine is cos_o = sqrt(1 - eta^2 (1 - mu^2)),
monotone in mu, so an outside bin [c_lo, c_hi) is the inside interval
[m(c_lo), m(c_hi)) with m(c) = sqrt(max(0, 1 - (1 - c^2) / eta^2)); m(0) = mu_c.
G[i, k] is the integral of (b) restricted to that mu interval. Summing over
cos bins that cover [0, 1] gives (b).

(d) The BSSRDF per (annulus, outside-cosine bin). A bin's S is (1 / (A Omega)) times the
integral of the exiting radiance over dA d(omega), i.e. of the flux divided by the outside
cosine: the integrand of (b)/(c) times 1 / cos_o(mu). With the transmittance written out,
t_s = 4 n c_i c_t / (c_i + n c_t)^2, t_p = 4 n c_i c_t / (n c_i + c_t)^2 (n = 1/eta leaving
the medium, c_i = mu, c_t = cos_o), T / cos_o = 2 n mu [1 / (mu + n c_t)^2 + 1 / (n mu + c_t)^2]
is finite where cos_o -> 0 (critical angle, and grazing at eta = 1, where T / cos_o = 1 / mu
and the integrand stays finite because the flux carries a factor mu).

Valid range: sigma_t > 0, albedo in [0, 1], g in (-1, 1) (tested from -0.9 to
0.95), eta > 0 (eta = 1 index matched), theta_i in [0, pi/2). Radii in mm,
edges increasing, the last edge may be inf.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import integrate, special

from .fresnel import critical_cosine, fresnel_reflectance

__all__ = [
    "hg_phase",
    "hg_azimuthal_integral",
    "single_scattering_total",
    "single_scattering_radial",
    "single_scattering_radial_cos",
    "inside_cosine_from_outside",
    "transmittance_over_cos_out",
]

_EPSABS = 1e-12
_EPSREL = 1e-11


def hg_phase(cos_theta, g: float):
    """Henyey-Greenstein phase function in 1/sr; integrates to 1 over the sphere."""
    c = np.asarray(cos_theta, dtype=np.float64)
    return (1.0 - g * g) / (4.0 * math.pi * (1.0 + g * g - 2.0 * g * c) ** 1.5)


def hg_azimuthal_integral(mu: float, g: float, sin_t: float, mu_t: float) -> float:
    """int_0^{2 pi} p(d0 . w) dphi for w = (sin th cos phi, sin th sin phi, mu),
    d0 = (sin_t, 0, -mu_t); closed form with the complete elliptic integral E (per sr * rad)."""
    sin_th = math.sqrt(max(0.0, 1.0 - mu * mu))
    c = 1.0 + g * g + 2.0 * g * mu_t * mu
    d = 2.0 * abs(g) * sin_t * sin_th
    m = 2.0 * d / (c + d)
    return (1.0 - g * g) / (4.0 * math.pi) * 4.0 * special.ellipe(m) / ((c - d) * math.sqrt(c + d))


def _check(albedo: float, g: float, eta: float) -> None:
    if not (0.0 <= albedo <= 1.0):
        raise ValueError(f"albedo must be in [0, 1], got {albedo}")
    if not (-1.0 < g < 1.0):
        raise ValueError(f"g must be in (-1, 1), got {g}")
    if not eta > 0.0:
        raise ValueError(f"eta must be positive, got {eta}")


def _peak_points(center: float, g: float, lo: float, hi: float) -> list[float]:
    """Break points around a phase-function peak at cosine ``center`` (width ~ (1-|g|)^2/|g|)."""
    if g == 0.0:
        return []
    width = (1.0 - abs(g)) ** 2 / (2.0 * abs(g))
    pts = {center}
    for k in (1.0, 4.0, 16.0, 64.0):
        pts.add(center - k * width)
        pts.add(center + k * width)
    return sorted(p for p in pts if lo < p < hi)


def single_scattering_total(albedo: float, g: float, eta: float, theta_i: float = 0.0) -> float:
    """Exact single-scattering diffuse reflectance Rd_single (dimensionless).

    Per unit incident power, including the entry transmission 1 - Fr(cos ti, eta) and
    the exit transmission; independent of sigma_t. ``theta_i`` in radians, [0, pi/2).
    """
    _check(albedo, g, eta)
    if not (0.0 <= theta_i < 0.5 * math.pi):
        raise ValueError("theta_i must be in [0, pi/2)")
    cos_i = math.cos(theta_i)
    sin_t = math.sin(theta_i) / eta
    if sin_t >= 1.0:
        return 0.0  # (eta < 1) no light enters
    mu_t = math.sqrt(1.0 - sin_t * sin_t)
    t_in = 1.0 - fresnel_reflectance(cos_i, eta)
    mu_c = critical_cosine(eta)

    def f(mu: float) -> float:
        t_out = 1.0 - fresnel_reflectance(mu, 1.0 / eta)
        return hg_azimuthal_integral(mu, g, sin_t, mu_t) * mu / (mu + mu_t) * t_out

    # For g < 0 the backward peak (-d0) is at mu = mu_t; for g > 0 the forward lobe is
    # below the horizon and the upper-hemisphere maximum is at grazing (mu -> 0).
    pts = _peak_points(mu_t if g < 0 else 0.0, g, mu_c, 1.0)
    val, _ = integrate.quad(f, mu_c, 1.0, points=pts or None,
                            epsabs=_EPSABS, epsrel=_EPSREL, limit=1000)
    return t_in * albedo * val


def inside_cosine_from_outside(cos_o, eta: float):
    """Inside cosine mu whose refracted outside cosine is ``cos_o``:
    m(c) = sqrt(max(0, 1 - (1 - c^2) / eta^2)); m(0) = critical cosine for eta > 1."""
    c = np.asarray(cos_o, dtype=np.float64)
    return np.sqrt(np.maximum(0.0, 1.0 - (1.0 - c * c) / (eta * eta)))


def _as_edges(edges, name: str, upper: float | None = None) -> np.ndarray:
    e = np.asarray(edges, dtype=np.float64).reshape(-1)
    if e.size < 2 or np.any(np.diff(e) <= 0.0) or e[0] < 0.0 or np.isnan(e).any():
        raise ValueError(f"{name} must be increasing, non-negative, at least two edges")
    if upper is not None and e[-1] > upper:
        raise ValueError(f"{name} must not exceed {upper}")
    return e


def transmittance_over_cos_out(mu: float, eta: float) -> float:
    """T(mu) / cos_o leaving the medium (inside cosine mu, relative index eta): see (d); 0 under
    total internal reflection."""
    n = 1.0 / eta
    c2 = 1.0 - (1.0 - mu * mu) / (n * n)
    if c2 <= 0.0:
        return 0.0
    ct = math.sqrt(c2)
    return 2.0 * n * mu * (1.0 / (mu + n * ct) ** 2 + 1.0 / (n * mu + ct) ** 2)


def _cumulative_radial(r_edges: np.ndarray, mu_bounds: np.ndarray, sigma_t: float,
                       albedo: float, g: float, eta: float, radiance: bool = False) -> np.ndarray:
    """C[e, k] = (1-Fr_0) a int_{mu_bounds[k]}^{mu_bounds[k+1]} 2 pi p(-mu) T(mu) mu/(1+mu)
    exp(-sigma_t r_e u(mu)) dmu, for all edges e and mu intervals k at once; with radiance=True
    the integrand has T(mu) / cos_o(mu) in place of T(mu) (the S integral, see (d))."""
    n_k = mu_bounds.size - 1
    tau = sigma_t * r_edges  # may contain inf
    finite = np.isfinite(tau)
    tau_f = np.where(finite, tau, 0.0)
    t_in = 1.0 - fresnel_reflectance(1.0, eta)
    inv_eta = 1.0 / eta
    two_pi = 2.0 * math.pi

    def f(mu: float) -> np.ndarray:
        out = np.zeros((tau.size, n_k))
        k = int(np.searchsorted(mu_bounds, mu, side="right")) - 1
        if k < 0 or k >= n_k:
            return out.ravel()
        t_out = transmittance_over_cos_out(mu, eta) if radiance else 1.0 - fresnel_reflectance(mu, inv_eta)
        base = two_pi * float(hg_phase(-mu, g)) * t_out * mu / (1.0 + mu)
        u = math.sqrt((1.0 + mu) / max(1.0 - mu, 1e-300))
        col = base * np.exp(-tau_f * u)
        out[:, k] = np.where(finite, col, 0.0)
        return out.ravel()

    lo, hi = float(mu_bounds[0]), float(mu_bounds[-1])
    if hi <= lo:
        return np.zeros((tau.size, n_k))
    pts = set(float(m) for m in mu_bounds[1:-1] if lo < m < hi)
    pts.update(_peak_points(1.0, g, lo, hi) if g < 0 else [])
    # Exponential transitions: exp(-tau u) drops where u ~ 1/tau, i.e. mu ~ (1/tau^2-1)/(1/tau^2+1)
    # for tau < 1 (near mu = 1); the adaptive rule resolves them, the points only help it.
    val, _err = integrate.quad_vec(f, lo, hi, epsabs=_EPSABS, epsrel=_EPSREL, norm="max",
                                   limit=20000, points=sorted(pts) or None)
    return t_in * albedo * np.asarray(val).reshape(tau.size, n_k)


def single_scattering_radial_cos(edges_mm, cos_edges, sigma_t: float, albedo: float,
                                 g: float, eta: float, quantity: str = "G") -> np.ndarray:
    """Single-scattering exitance G per (annulus, outside-cosine bin), normal incidence.

    ``edges_mm``: radial edges in mm (n_r + 1, increasing, last may be inf).
    ``cos_edges``: edges in the OUTSIDE cosine cos_o (n_cos + 1, increasing, in [0, 1]).
    Returns an [n_r, n_cos] array of the fraction of incident power (dimensionless) that
    leaves after exactly one scattering through each bin; at normal incidence it all
    leaves radially (phi_o = 0). quantity="S": the integral of the flux / cos_o instead
    (the radiance integrated over dA d omega, see (d)); divide it by area * solid angle for
    the bin's BSSRDF.
    """
    if quantity not in ("G", "S"):
        raise ValueError(f"quantity must be 'G' or 'S', got {quantity!r}")
    _check(albedo, g, eta)
    if not sigma_t > 0.0:
        raise ValueError("sigma_t must be positive")
    r = _as_edges(edges_mm, "edges_mm")
    c = _as_edges(cos_edges, "cos_edges", upper=1.0)
    mu_b = inside_cosine_from_outside(c, eta)
    cum = _cumulative_radial(r, mu_b, sigma_t, albedo, g, eta, radiance=quantity == "S")
    return cum[:-1, :] - cum[1:, :]


def single_scattering_radial(edges_mm, sigma_t: float, albedo: float, g: float,
                             eta: float) -> np.ndarray:
    """Single-scattering flux per annulus G(r_lo, r_hi), normal incidence (dimensionless).

    ``edges_mm``: radial edges in mm (increasing; last may be inf); returns n_r values.
    Rd_r = G / (pi (r_hi^2 - r_lo^2)) in 1/mm^2. Over [0, inf) it sums to
    ``single_scattering_total(albedo, g, eta, 0)``.
    """
    return single_scattering_radial_cos(edges_mm, [0.0, 1.0], sigma_t, albedo, g, eta)[:, 0]
