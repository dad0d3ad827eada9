"""Diffusion models of the radial profile at normal incidence (numpy, torch-free).

Three models renderers use in place of a measured table, drawn beside ours in the exports:

* the **classical dipole** (Jensen, Marschner, Levoy and Hanrahan 2001, "A Practical Model for
  Subsurface Light Transport"; the seed slides "Dipole diffusion approximation"),
* **photon beam diffusion** (Habel, Christensen and Jarosz 2013) as pbrt-v3 implements it in
  ``BeamDiffusionSS`` / ``BeamDiffusionMS`` (pbrt 3rd ed., sec. 15.5; the profile its
  ``TabulatedBSSRDF`` tabulates, seed ``pbrt-15.4``),
* the **Christensen-Burley** fitted relation between single-scattering and total albedo
  (Christensen and Burley 2015, "Approximate Reflectance Profiles for Efficient Subsurface
  Scattering", Pixar technical memo 15-04).

Conventions (:mod:`workers.walk.conventions`): the medium fills z < 0, light enters at the origin
along -z (normal incidence), lengths in mm and coefficients in 1/mm (pass sigma_t = 1 for optical
units). Every profile here is **per unit power that entered the medium** (the entry Fresnel
factor 1 - R_spec excluded, as in pbrt's table); multiply by 1 - R_spec to compare with the
stored tables, which are per unit incident power. A profile Rd(r) is flux leaving per unit area
[1/mm^2]; 2 pi r Rd(r) is its density in r, integrating to the total diffuse reflectance.
The functions are pure and elementwise in r.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "fresnel_reflectance",
    "fresnel_moment",
    "hg_phase",
    "dipole_rd",
    "dipole_total_rd",
    "dipole_exitance",
    "dipole_exitance_total",
    "pbd_single",
    "pbd_multiple",
    "pbd_rd",
    "burley_reduced_albedo",
    "burley_total_rd",
    "reduced_albedo",
    "albedo_from_reduced",
]

_INV_4PI = 1.0 / (4.0 * math.pi)
_GL_S, _GL_W = np.polynomial.legendre.leggauss(64)
_GL_S, _GL_W = 0.5 * (_GL_S + 1.0), 0.5 * _GL_W  # Gauss-Legendre on [0, 1]


def fresnel_reflectance(cos_i, eta: float) -> np.ndarray:
    """Unpolarised Fresnel reflectance of a smooth dielectric, numpy (the torch-free twin of
    :func:`workers.walk.optics.fresnel_dielectric`, same formula and arguments).

    cos_i in [0, 1] on the incident side, eta = n_transmitted / n_incident; with
    sin_t^2 = (1 - cos_i^2) / eta^2, r_s = (cos_i - eta cos_t) / (cos_i + eta cos_t),
    r_p = (eta cos_i - cos_t) / (eta cos_i + cos_t), Fr = (r_s^2 + r_p^2) / 2, and 1 under total
    internal reflection (Born and Wolf, sec. 1.5).
    """
    c = np.clip(np.asarray(cos_i, dtype=np.float64), 0.0, 1.0)
    if eta == 1.0:
        return np.zeros_like(c)  # no interface: nothing reflects, even at grazing incidence
    cos2_t = 1.0 - (1.0 - c * c) / (eta * eta)
    cos_t = np.sqrt(np.maximum(cos2_t, 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):  # 0/0 only at cos_i = cos_t = 0 (TIR below)
        r_s = (c - eta * cos_t) / (c + eta * cos_t)
        r_p = (eta * c - cos_t) / (eta * c + cos_t)
    return np.where(cos2_t <= 0.0, 1.0, 0.5 * (r_s * r_s + r_p * r_p))


def fresnel_moment(i: int, eta: float) -> float:
    """i-th Fresnel moment of the boundary seen from inside a medium of relative index eta,

        FM_i(eta) = int_0^1 Fr(mu, 1/eta) mu^i dmu,

    the quantity pbrt's ``FresnelMoment1`` / ``FresnelMoment2`` fit with polynomials
    (2 FM_1 is the diffuse internal reflectance F_dr of the dipole's boundary condition).
    Exact up to quadrature: below the critical cosine mu_c = sqrt(1 - 1/eta^2) (eta > 1) Fr = 1
    and that part is integrated in closed form; above it the substitution
    mu^2 = mu_c^2 + (1 - mu_c^2) s^2 makes the integrand smooth in s (the square root of
    Snell's law becomes linear in s), so 64-point Gauss-Legendre is exact to ~1e-15.
    """
    mu_c2 = max(0.0, 1.0 - 1.0 / (eta * eta))
    below = math.sqrt(mu_c2) ** (i + 1) / (i + 1)
    mu = np.sqrt(mu_c2 + (1.0 - mu_c2) * _GL_S * _GL_S)
    jac = (1.0 - mu_c2) * _GL_S / mu  # dmu / ds
    return below + float(np.sum(_GL_W * fresnel_reflectance(mu, 1.0 / eta) * mu**i * jac))


def hg_phase(cos_theta, g: float) -> np.ndarray:
    """Henyey-Greenstein phase function per steradian, (1 - g^2) / (4 pi (1 + g^2 - 2 g cos)^1.5),
    cos between the directions of travel before and after scattering (as :func:`workers.walk.optics.hg_pdf`)."""
    denom = 1.0 + g * g - 2.0 * g * np.asarray(cos_theta, dtype=np.float64)
    return _INV_4PI * (1.0 - g * g) / (denom * np.sqrt(denom))


def reduced_albedo(albedo, g: float):
    """alpha' = sigma_s' / sigma_t' = alpha (1 - g) / (1 - alpha g) for albedo alpha = sigma_s / sigma_t."""
    a = np.asarray(albedo, dtype=np.float64)
    return a * (1.0 - g) / (1.0 - a * g)


def albedo_from_reduced(albedo_reduced, g: float):
    """Inverse of :func:`reduced_albedo`: alpha = alpha' / (1 - g + g alpha')."""
    a = np.asarray(albedo_reduced, dtype=np.float64)
    return a / (1.0 - g + g * a)


# ---- classical dipole (Jensen et al. 2001) ------------------------------------------------------


def _dipole_geometry(sigma_a: float, sigma_s_reduced: float, eta: float) -> tuple[float, float, float, float]:
    """(alpha', sigma_tr, z_r, z_v) of the dipole: sigma_t' = sigma_a + sigma_s', alpha' = sigma_s'/sigma_t',
    sigma_tr = sqrt(3 sigma_a sigma_t'), z_r = 1/sigma_t', z_v = z_r (1 + 4 A / 3),
    A = (1 + F_dr) / (1 - F_dr), F_dr = 2 FM_1(eta) (exact, not the Egan-Hilgeman fit)."""
    sigma_t_r = sigma_a + sigma_s_reduced
    f_dr = 2.0 * fresnel_moment(1, eta)
    a_boundary = (1.0 + f_dr) / (1.0 - f_dr)
    z_r = 1.0 / sigma_t_r
    return sigma_s_reduced / sigma_t_r, math.sqrt(3.0 * sigma_a * sigma_t_r), z_r, z_r * (1.0 + 4.0 * a_boundary / 3.0)


def dipole_rd(r, sigma_a: float, sigma_s_reduced: float, eta: float) -> np.ndarray:
    """Classical dipole diffuse reflectance profile Rd(r) [1/mm^2] (Jensen et al. 2001, eq. 5):

        Rd(r) = alpha' / (4 pi) [ z_r (1 + sigma_tr d_r) e^{-sigma_tr d_r} / d_r^3
                                + z_v (1 + sigma_tr d_v) e^{-sigma_tr d_v} / d_v^3 ],

    d_{r,v} = sqrt(r^2 + z_{r,v}^2), the real source at depth z_r = 1/sigma_t' and the negative
    (image) source at height z_v (see :func:`_dipole_geometry`). Per unit power entered; its
    integral over the plane is :func:`dipole_total_rd`. Multiple scattering only (the model has
    no single-scattering term). sigma_a >= 0, sigma_s' > 0.
    """
    alpha_r, s_tr, z_r, z_v = _dipole_geometry(sigma_a, sigma_s_reduced, eta)
    r2 = np.asarray(r, dtype=np.float64) ** 2
    d_r, d_v = np.sqrt(r2 + z_r * z_r), np.sqrt(r2 + z_v * z_v)
    return alpha_r * _INV_4PI * (z_r * (1.0 + s_tr * d_r) * np.exp(-s_tr * d_r) / d_r**3
                                 + z_v * (1.0 + s_tr * d_v) * np.exp(-s_tr * d_v) / d_v**3)


def dipole_total_rd(albedo_reduced, eta: float):
    """Total diffuse reflectance of the dipole (Jensen et al. 2001, eq. 6 integrated):

        Rd = (alpha'/2) (1 + e^{-(4/3) A sqrt(3 (1 - alpha'))}) e^{-sqrt(3 (1 - alpha'))},

    from int_0^inf 2 pi r z (1 + s d) e^{-s d} / (4 pi d^3) dr = e^{-s z} / 2 for each source
    (sigma_tr z_r = sqrt(3 (1 - alpha')), sigma_tr z_v = that times 1 + 4 A / 3). Per unit power
    entered; alpha' = sigma_s' / sigma_t' in [0, 1]. Elementwise in alpha'."""
    a = np.asarray(albedo_reduced, dtype=np.float64)
    f_dr = 2.0 * fresnel_moment(1, eta)
    a_boundary = (1.0 + f_dr) / (1.0 - f_dr)
    root = np.sqrt(3.0 * (1.0 - a))
    return 0.5 * a * (1.0 + np.exp(-4.0 / 3.0 * a_boundary * root)) * np.exp(-root)


# ---- photon beam diffusion (Habel et al. 2013; pbrt-v3 BeamDiffusionMS / SS) --------------------


def dipole_exitance(r, z_r, z_v, sigma_tr: float, d: float, c_phi: float, c_e: float) -> np.ndarray:
    """Exitance [1/mm^2] of one dipole with a unit real source at depth z_r and its image at
    z_v < 0 (the "better dipole" boundary of d'Eon and Irving 2011, pbrt eq. 15.27-15.32):

        phi(r)  = (1 / (4 pi D)) (e^{-s d_r} / d_r - e^{-s d_v} / d_v)              fluence
        -n.E(r) = (1 / 4 pi) (z_r (1 + s d_r) e^{-s d_r} / d_r^3 - z_v (1 + s d_v) e^{-s d_v} / d_v^3)
        E_d(r)  = c_phi phi(r) + c_E (-n.E(r)),

    s = sigma_tr, d_{r,v} = sqrt(r^2 + z_{r,v}^2). Broadcasts r against z_r / z_v. Its integral
    over the plane is :func:`dipole_exitance_total`.
    """
    r2 = np.asarray(r, dtype=np.float64) ** 2
    d_r, d_v = np.sqrt(r2 + z_r * z_r), np.sqrt(r2 + z_v * z_v)
    e_r, e_v = np.exp(-sigma_tr * d_r), np.exp(-sigma_tr * d_v)
    phi = _INV_4PI / d * (e_r / d_r - e_v / d_v)
    flux = _INV_4PI * (z_r * (1.0 + sigma_tr * d_r) * e_r / d_r**3 - z_v * (1.0 + sigma_tr * d_v) * e_v / d_v**3)
    return c_phi * phi + c_e * flux


def dipole_exitance_total(z_r, z_v, sigma_tr: float, d: float, c_phi: float, c_e: float):
    """int_0^inf 2 pi r :func:`dipole_exitance` dr in closed form (z_v < 0 < z_r):

        c_phi (e^{-s z_r} - e^{-s |z_v|}) / (2 D s) + c_E (e^{-s z_r} + e^{-s |z_v|}) / 2,

    since int 2 pi r e^{-s d} / (4 pi d) dr = e^{-s z} / (2 s) and
    int 2 pi r z (1 + s d) e^{-s d} / (4 pi d^3) dr = e^{-s z} / 2 (d from z to inf). At s = 0
    the first term is its limit c_phi (|z_v| - z_r) / (2 D)."""
    z_r, zv_abs = np.asarray(z_r, dtype=np.float64), np.abs(np.asarray(z_v, dtype=np.float64))
    e_r, e_v = np.exp(-sigma_tr * z_r), np.exp(-sigma_tr * zv_abs)
    # (e_r - e_v) / s without cancellation: e_r (1 - e^{-s (|z_v| - z_r)}) / s, -> |z_v| - z_r at s = 0.
    gap = zv_abs - z_r
    ratio = gap if sigma_tr == 0.0 else -np.expm1(-sigma_tr * gap) / sigma_tr
    return c_phi * e_r * ratio / (2.0 * d) + c_e * 0.5 * (e_r + e_v)


def _midpoint_exponential(n: int, rate: float, shift=0.0) -> np.ndarray:
    """pbrt's depth samples t_i = shift - ln(1 - (i + 1/2) / n) / rate, i = 0..n-1: the midpoint
    rule in u of an integral against rate e^{-rate (t - shift)} dt on [shift, inf)."""
    u = (np.arange(n, dtype=np.float64) + 0.5) / n
    return np.asarray(shift, dtype=np.float64)[..., None] - np.log1p(-u) / rate


def pbd_multiple(r, sigma_a: float, sigma_s: float, g: float, eta: float, n_depth: int = 100) -> np.ndarray:
    """Multiple-scattering part of photon beam diffusion [1/mm^2], as pbrt-v3 ``BeamDiffusionMS``:

        Rd_ms(r) = int_0^inf sigma_t' e^{-sigma_t' z} kappa(z) rho'^2 E_d(r; z) dz,

    with sigma_s' = sigma_s (1 - g), sigma_t' = sigma_a + sigma_s', rho' = sigma_s'/sigma_t',
    Grosjean's D_G = (2 sigma_a + sigma_s') / (3 sigma_t'^2), sigma_tr = sqrt(sigma_a / D_G),
    extrapolation z_e = -2 D_G (1 + 3 FM_2) / (1 - 2 FM_1), image z_v = -z + 2 z_e,
    c_phi = (1 - 2 FM_1) / 4, c_E = (1 - 3 FM_2) / 2 (:func:`fresnel_moment`, exact here where
    pbrt uses its polynomial fits), kappa = 1 - e^{-2 sigma_t' (d_r + z)}, E_d of
    :func:`dipole_exitance`. The depth integral is pbrt's: ``n_depth`` midpoint samples in the
    exponential's quantile. Per unit power entered, exit Fresnel included.
    """
    s_red = sigma_s * (1.0 - g)
    st_red = sigma_a + s_red
    rho_red = s_red / st_red
    d_g = (2.0 * sigma_a + s_red) / (3.0 * st_red * st_red)
    sigma_tr = math.sqrt(sigma_a / d_g)
    fm1, fm2 = fresnel_moment(1, eta), fresnel_moment(2, eta)
    z_e = -2.0 * d_g * (1.0 + 3.0 * fm2) / (1.0 - 2.0 * fm1)
    c_phi, c_e = 0.25 * (1.0 - 2.0 * fm1), 0.5 * (1.0 - 3.0 * fm2)
    z_r = _midpoint_exponential(n_depth, st_red)
    r = np.asarray(r, dtype=np.float64)[..., None]
    e_d = dipole_exitance(r, z_r, -z_r + 2.0 * z_e, sigma_tr, d_g, c_phi, c_e)
    kappa = -np.expm1(-2.0 * st_red * (np.sqrt(r * r + z_r * z_r) + z_r))
    return np.mean(kappa * rho_red * rho_red * e_d, axis=-1)


def pbd_single(r, sigma_a: float, sigma_s: float, g: float, eta: float, n_depth: int = 100) -> np.ndarray:
    """Single-scattering part of photon beam diffusion [1/mm^2], as pbrt-v3 ``BeamDiffusionSS``:
    the exact single scattering of the normally incident beam (depth t on the axis) to the exit
    point at radius r,

        Rd_ss(r) = int_{t_c}^inf sigma_s e^{-sigma_t t} p(-t/d) e^{-sigma_t d} T(t/d) (t/d) / d^2 dt,

    d = sqrt(r^2 + t^2), p the HG phase function (the beam travels along -z; the path to the exit
    point leaves at cosine -t/d to it), T(mu) = 1 - Fr(mu, 1/eta) the exit transmittance, and
    t_c = r sqrt(eta^2 - 1) the depth above which the exit is not totally internally reflected
    (0 for eta <= 1). The integral is pbrt's: t - t_c ~ sigma_t e^{-sigma_t (t - t_c)},
    ``n_depth`` midpoint samples in its quantile. Per unit power entered.
    """
    sigma_t = sigma_a + sigma_s
    r = np.asarray(r, dtype=np.float64)
    t_c = r * math.sqrt(max(eta * eta - 1.0, 0.0))
    t = _midpoint_exponential(n_depth, sigma_t, t_c)
    r = r[..., None]
    d = np.sqrt(r * r + t * t)
    cos_o = t / d
    f = (sigma_s / sigma_t) * np.exp(-sigma_t * (d + t_c[..., None])) / (d * d) * hg_phase(-cos_o, g) \
        * (1.0 - fresnel_reflectance(cos_o, 1.0 / eta)) * cos_o
    return np.mean(f, axis=-1)


def pbd_rd(r, sigma_a: float, sigma_s: float, g: float, eta: float, n_depth: int = 100) -> np.ndarray:
    """Photon beam diffusion Rd(r) = :func:`pbd_single` + :func:`pbd_multiple` [1/mm^2]; pbrt's
    table entry at optical radius r (sigma_t = 1, sigma_s = rho) is 2 pi r pbd_rd(r)."""
    return pbd_single(r, sigma_a, sigma_s, g, eta, n_depth) + pbd_multiple(r, sigma_a, sigma_s, g, eta, n_depth)


# ---- Christensen-Burley ------------------------------------------------------------------------


def burley_reduced_albedo(total_rd):
    """Christensen and Burley's (2015) fitted inversion of the total diffuse reflectance A of a
    semi-infinite medium to its (reduced) single-scattering albedo,

        alpha' = 1 - (4.09712 + 4.20863 A - sqrt(9.59217 + 41.6808 A + 17.7126 A^2))^2,

    as printed. It fits the total reflectance under *diffuse* illumination of an *index-matched*
    half space of *isotropic* scatterers: within 2.5e-3 of the exact value from Chandrasekhar's
    H-function (tests/workers/test_diffusion.py); renderers apply it at any eta and to the
    reduced albedo alpha' for g != 0. Maps [0, 1] onto [0, 1] monotonically (0 -> 0, 1 -> 1 to 5
    digits). Elementwise."""
    a = np.asarray(total_rd, dtype=np.float64)
    k = 4.09712 + 4.20863 * a - np.sqrt(9.59217 + 41.6808 * a + 17.7126 * a * a)
    return 1.0 - k * k


def burley_total_rd(albedo_reduced, iterations: int = 60):
    """The total diffuse reflectance A the Christensen-Burley fit gives for reduced albedo
    alpha', i.e. :func:`burley_reduced_albedo` inverted by bisection on A in [0, 1] (the fit is
    increasing there; 60 halvings reach float64 resolution). Elementwise; alpha' in [0, 1]."""
    target = np.asarray(albedo_reduced, dtype=np.float64)
    lo, hi = np.zeros_like(target), np.ones_like(target)
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        below = burley_reduced_albedo(mid) < target
        lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
    return 0.5 * (lo + hi)
