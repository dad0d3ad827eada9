"""Pure physics kernels over tensors: free paths, Henyey-Greenstein, Fresnel, refraction.

Directions and cosines follow :mod:`workers.walk.conventions`.  Every function takes tensors and
explicit uniforms, works elementwise (any shape, float32 or float64), branches with masks, and
never mutates its inputs.  Each is tested against its pdf or a closed form in tests/.
"""

from __future__ import annotations

import math

import torch

__all__ = [
    "sample_exponential",
    "exponential_pdf",
    "hg_pdf",
    "sample_hg",
    "fresnel_dielectric",
    "refracted_cos",
    "fresnel_transmittance",
    "transmittance_cos_ratio",
    "scatter_direction",
    "incident_refracted_direction",
]

INV_4PI = 1.0 / (4.0 * math.pi)


def sample_exponential(u: torch.Tensor) -> torch.Tensor:
    """Optical free path s = -ln(u) for u in (0, 1]; pdf exp(-s) on [0, inf).

    Divide by sigma_t for a length in mm.  u must exclude 0 (use :func:`workers.walk.rng.uniform_open`).
    """
    return -torch.log(u)


def exponential_pdf(s: torch.Tensor) -> torch.Tensor:
    """pdf of :func:`sample_exponential`: exp(-s) for s >= 0, 0 otherwise."""
    return torch.where(s >= 0, torch.exp(-s), torch.zeros_like(s))


def hg_pdf(cos_theta: torch.Tensor, g: torch.Tensor | float) -> torch.Tensor:
    """Henyey-Greenstein phase function per steradian, 1/sr.

        p(cos) = (1 - g^2) / (4 pi (1 + g^2 - 2 g cos)^(3/2)),   |g| < 1,

    normalised over the sphere, mean cosine g (Henyey and Greenstein 1941).  cos_theta is the
    cosine between the directions of travel before and after scattering.
    """
    denom = 1.0 + g * g - 2.0 * g * cos_theta
    # denom >= (1 - |g|)^2 > 0 for |g| < 1; the clamp only guards rounding at cos = +-1.
    denom = torch.clamp(denom, min=1e-30)
    return INV_4PI * (1.0 - g * g) / (denom * torch.sqrt(denom))


def sample_hg(u: torch.Tensor, g: torch.Tensor | float, branch: str = "mixed") -> torch.Tensor:
    """cos(theta) distributed by Henyey-Greenstein, from u uniform in [0, 1].

    Inverting the CDF gives, for a = |g| > 0,
        cos(a, u) = (1 + a^2 - s^2) / (2 a),   s = (1 - a^2) / (1 - a + 2 a u),
    u = 0 and 1 mapping to -1 and +1; a negative g mirrors it: cos(g, u) = -cos(|g|, 1 - u).
    This form keeps float32 precision up to |g| -> 1 but cancels as g -> 0, so for |g| < 0.1 the
    same expression expanded with t = 2u - 1,
        cos = (t + (g/2) (3 + t^2 + 2 g t + g^2 (t^2 - 1))) / (1 + g t)^2,
    is used instead: no division by g, exactly t (isotropic) at g = 0, and no cancellation for
    small |g| (it does cancel near t = -1 when g -> 1, hence the two branches).
    (The seed slides print the first form with -1/|2g|: a sign typo, wrong for g > 0.)
    branch = "large" or "small" promises every |g| is >= 0.1 or < 0.1, so only that expression is
    evaluated (the walk knows this from its media); "mixed" selects per element.
    """
    g = torch.as_tensor(g, dtype=u.dtype)
    if branch == "small":
        return _hg_small(u, g)
    a = torch.abs(g)
    # Mirror negative g onto positive: cos(g, u) = -cos(|g|, 1 - u).
    v = torch.where(g < 0, 1.0 - u, u)
    a_safe = torch.clamp(a, min=0.1)  # the large-|g| branch is only selected for |g| >= 0.1
    one_minus_a = 1.0 - a_safe  # exact in floating point for a >= 0.5 (Sterbenz)
    # (1 - a)(1 + a), not 1 - a*a: the rounding of a*a would dominate 1 - a^2 as a -> 1.
    s = one_minus_a * (1.0 + a_safe) / (one_minus_a + 2.0 * a_safe * v)
    cos_large = (1.0 + a_safe * a_safe - s * s) / (2.0 * a_safe)
    cos_large = torch.where(g < 0, -cos_large, cos_large)
    if branch == "large":
        return torch.clamp(cos_large, -1.0, 1.0)
    cos = torch.where(a >= 0.1, cos_large, _hg_small(u, g))
    # Rounding can leave |cos| a few ulp above 1; it must stay a cosine.
    return torch.clamp(cos, -1.0, 1.0)


def _hg_small(u: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """The expanded inversion of :func:`sample_hg` (accurate for |g| < 0.1), clamped to [-1, 1]."""
    t = 2.0 * u - 1.0
    d = 1.0 + g * t
    cos = (t + 0.5 * g * (3.0 + t * t + 2.0 * g * t + g * g * (t * t - 1.0))) / (d * d)
    return torch.clamp(cos, -1.0, 1.0)


def fresnel_dielectric(cos_i: torch.Tensor, eta: torch.Tensor | float) -> torch.Tensor:
    """Unpolarised Fresnel reflectance of a smooth dielectric interface.

    cos_i >= 0 is the cosine of the incident direction with the normal on the incident side;
    eta = n_transmitted / n_incident.  With sin_t^2 = (1 - cos_i^2) / eta^2 and cos_t = sqrt(1 - sin_t^2),

        r_s = (cos_i - eta cos_t) / (cos_i + eta cos_t)
        r_p = (eta cos_i - cos_t) / (eta cos_i + cos_t)
        Fr  = (r_s^2 + r_p^2) / 2,

    and Fr = 1 under total internal reflection (sin_t^2 >= 1).  Entering the medium use eta;
    leaving it, 1/eta (Born and Wolf, Principles of Optics, sec. 1.5; pbrt-v4 FrDielectric).
    """
    cos_i = torch.clamp(cos_i, 0.0, 1.0)
    if isinstance(eta, (int, float)) and eta == 1.0:
        # No interface (a constant known when the walk is compiled): nothing reflects.
        return torch.zeros_like(cos_i)
    cos2_t = 1.0 - (1.0 - cos_i * cos_i) / (eta * eta)
    # eta = 1 (no interface): cos_t = cos_i exactly, so Fr = 0 even at grazing incidence, where
    # 1 - cos_i^2 rounds to 1 and the line above would report total internal reflection.
    cos2_t = torch.where(torch.as_tensor(eta) == 1.0, cos_i * cos_i, cos2_t)
    tir = cos2_t <= 0.0
    cos_t = torch.sqrt(torch.clamp(cos2_t, min=0.0))
    r_s = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
    r_p = (eta * cos_i - cos_t) / (eta * cos_i + cos_t)
    fr = 0.5 * (r_s * r_s + r_p * r_p)
    if not isinstance(eta, (int, float)):
        # cos_i = 0 with a tensor eta = 1 gives 0/0 above; no interface, nothing reflects.
        fr = torch.where(torch.isnan(fr), torch.zeros_like(fr), fr)
    return torch.where(tir, torch.ones_like(fr), fr)


def refracted_cos(cos_i: torch.Tensor, eta: torch.Tensor | float) -> torch.Tensor:
    """Cosine of the refracted direction, Snell's law: sqrt(1 - (1 - cos_i^2) / eta^2).

    eta = n_transmitted / n_incident; 0 where the ray is totally internally reflected.  Computed
    as sqrt((eta^2 - 1 + cos_i^2) / eta^2): at eta = 1 that is exactly |cos_i| (the form
    1 - (1 - cos_i^2) rounds to 0 for cos_i below ~2e-4 in float32, 1e-8 in float64, which made
    grazing exits look totally reflected while their transmittance was 1).
    """
    cos2_t = (eta * eta - 1.0 + cos_i * cos_i) / (eta * eta)
    return torch.sqrt(torch.clamp(cos2_t, min=0.0))


def _cos_t_and_ratio(cos_i: torch.Tensor, eta: torch.Tensor | float):
    """(cos_t, 2 eta [1 / (cos_i + eta cos_t)^2 + 1 / (eta cos_i + cos_t)^2]); see below."""
    cos_i = torch.clamp(cos_i, 0.0, 1.0)
    cos_t = refracted_cos(cos_i, eta)
    a = cos_i + eta * cos_t
    b = eta * cos_i + cos_t
    # a, b > 0 except at cos_i = cos_t = 0 (eta = 1, grazing), handled by the callers.
    return cos_i, cos_t, 2.0 * eta * (1.0 / torch.clamp(a * a, min=1e-30) + 1.0 / torch.clamp(b * b, min=1e-30))


def fresnel_transmittance(cos_i: torch.Tensor, eta: torch.Tensor | float) -> torch.Tensor:
    """Unpolarised Fresnel transmittance T = 1 - Fr, formed without the cancellation of 1 - Fr.

    With t_s = 1 - r_s^2 = 4 eta cos_i cos_t / (cos_i + eta cos_t)^2 and
    t_p = 1 - r_p^2 = 4 eta cos_i cos_t / (eta cos_i + cos_t)^2 (r_s, r_p as in
    :func:`fresnel_dielectric`), T = (t_s + t_p) / 2; 0 under total internal reflection, 1 at
    eta = 1.  Accurate where T is small (near the critical angle), where 1 - Fr keeps only the
    rounding of Fr.
    """
    if isinstance(eta, (int, float)) and eta == 1.0:
        return torch.ones_like(cos_i)  # no interface
    cos_i, cos_t, k = _cos_t_and_ratio(cos_i, eta)
    return cos_i * cos_t * k


def transmittance_cos_ratio(cos_i: torch.Tensor, eta: torch.Tensor | float) -> torch.Tensor:
    """T cos_i / cos_t, the factor that turns a transmitted flux into radiance, bounded.

    A flux f ~ T cos_i (per unit area, per unit solid angle inside) crossing the interface leaves
    as radiance f / cos_t outside; T / cos_t stays finite where cos_t -> 0 (T vanishes like
    cos_t at the critical angle), and at eta = 1 the ratio is exactly 1, however grazing:
        T cos_i / cos_t = 2 eta cos_i^2 [1 / (cos_i + eta cos_t)^2 + 1 / (eta cos_i + cos_t)^2].
    0 under total internal reflection.  Dividing G by a float cos_o instead gave S = 1e17-1e24
    in the grazing bin at eta = 1, where float32 cos_o rounded to 0.
    """
    if isinstance(eta, (int, float)) and eta == 1.0:
        return torch.ones_like(cos_i)  # no interface: the radiance crosses unchanged
    cos_i, cos_t, k = _cos_t_and_ratio(cos_i, eta)
    return torch.where(cos_t > 0.0, cos_i * cos_i * k, torch.zeros_like(k))


def scatter_direction(
    ux: torch.Tensor, uy: torch.Tensor, uz: torch.Tensor, cos_theta: torch.Tensor, phi: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Rotate the unit direction u by polar angle theta (given by its cosine) and azimuth phi.

    The new direction u' satisfies u . u' = cos_theta; phi is measured about u in the frame of
    the classic MCML update (Wang, Jacques and Zheng 1995, eq. 3.24):

        u'x = sin(t) (ux uz cos(p) - uy sin(p)) / sqrt(1 - uz^2) + ux cos(t)
        u'y = sin(t) (uy uz cos(p) + ux sin(p)) / sqrt(1 - uz^2) + uy cos(t)
        u'z = -sin(t) cos(p) sqrt(1 - uz^2) + uz cos(t)

    with sqrt(1 - uz^2) computed as sqrt(ux^2 + uy^2); where u is exactly (anti)parallel to z
    (the frame degenerates), u' = (sin t cos p, sin t sin p, sign(uz) cos t).  The result is renormalised, so float32 rounding does not accumulate over
    thousands of scattering events.
    """
    sin_theta = torch.sqrt(torch.clamp(1.0 - cos_theta * cos_theta, min=0.0))
    cos_phi = torch.cos(phi)
    sin_phi = torch.sin(phi)
    # sqrt(ux^2 + uy^2) rather than sqrt(1 - uz^2): the latter loses float32 precision as |uz| -> 1.
    den = torch.sqrt(ux * ux + uy * uy)
    polar = den < 1e-20  # u is (anti)parallel to z: the frame degenerates
    den_safe = torch.where(polar, torch.ones_like(den), den)
    nx = sin_theta * (ux * uz * cos_phi - uy * sin_phi) / den_safe + ux * cos_theta
    ny = sin_theta * (uy * uz * cos_phi + ux * sin_phi) / den_safe + uy * cos_theta
    nz = -sin_theta * cos_phi * den + uz * cos_theta
    nx = torch.where(polar, sin_theta * cos_phi, nx)
    ny = torch.where(polar, sin_theta * sin_phi, ny)
    nz = torch.where(polar, torch.where(uz >= 0, cos_theta, -cos_theta), nz)
    inv_norm = torch.rsqrt(nx * nx + ny * ny + nz * nz)
    return nx * inv_norm, ny * inv_norm, nz * inv_norm


def incident_refracted_direction(theta_i_rad: float, eta: float) -> tuple[float, float, float]:
    """Direction inside the medium of the ray incident along (sin ti, 0, -cos ti), Snell's law.

    Returns (sin ti / eta, 0, -sqrt(1 - sin^2 ti / eta^2)); for eta < 1 an incidence beyond the
    critical angle does not enter, which the spec validation rejects before this is called.
    """
    sin_t = math.sin(theta_i_rad) / eta
    if sin_t >= 1.0:
        raise ValueError(f"incidence {math.degrees(theta_i_rad)} deg is beyond the critical angle for eta={eta}")
    return sin_t, 0.0, -math.sqrt(1.0 - sin_t * sin_t)
