"""pbrt's tabulated BSSRDF: the table and its sampling side (numpy, torch-free).

The table (pbrt-v3 ``BSSRDFTable``; pbrt 3rd ed. sec. 11.4.2 and 15.4.2) holds, for a medium
of unit extinction sigma_t = 1 with phase parameter g and relative index eta,

    rhoSamples[n_rho]            single-scattering albedos rho = sigma_s / sigma_t
    radiusSamples[n_r]           optical radii r sigma_t, radiusSamples[0] = 0
    profile[n_rho, n_r]          2 pi r Sr(rho, r): the density in r of the exitance per unit
                                 power entered (row-major, rho outer)
    rhoEff[n_rho]                int profile dr (Catmull-Rom), the effective albedo
    profileCDF[n_rho, n_r]       running integral of profile at the nodes, unnormalised

and a channel of optics (sigma_t, rho) evaluates it in world units (1/mm^2) as

    Sr(r)     = sigma_t^2 P(rho, r sigma_t) / (2 pi r sigma_t),   P the tensor Catmull-Rom
                spline of ``profile`` (0 outside the nodes), clamped to >= 0,
    Pdf_Sr(r) = Sr(r) / rhoEff(rho)                                 (per unit area),
    Sample_Sr(u) = radius with density 2 pi r Pdf_Sr(r) (inverting the interpolated CDF),
    r_max     = Sample_Sr(0.999), beyond which pbrt's probe rays stop.

This module is our own implementation of those four, used to prove an exported table works
the way pbrt would use it (tests/workers/test_tabulated.py), and :func:`beam_diffusion_table`,
pbrt's own table from photon beam diffusion, to compare with.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from schema.bins import pbrt_radius_nodes

from .catmull_rom import catmull_rom, catmull_rom_weights, integrate_catmull_rom, sample_catmull_rom_2d
from .diffusion import pbd_rd

__all__ = [
    "BSSRDFTable",
    "pbrt_rho_samples",
    "beam_diffusion_table",
    "sr",
    "pdf_sr",
    "sample_sr",
    "r_max",
    "R_MAX_QUANTILE",
]

R_MAX_QUANTILE = 0.999
"""pbrt's ``Sample_Sp``: r_max = Sample_Sr(0.999)."""


def pbrt_rho_samples(count: int) -> np.ndarray:
    """pbrt's albedo nodes rho_i = (1 - exp(-8 i / (n - 1))) / (1 - exp(-8)), i = 0..n-1: from
    exactly 0 to exactly 1, dense near 1."""
    if count < 2:
        raise ValueError(f"pbrt's albedo nodes need count >= 2; received {count}")
    i = np.arange(count, dtype=np.float64)
    rho = -np.expm1(-8.0 * i / (count - 1)) / -math.expm1(-8.0)
    rho[0], rho[-1] = 0.0, 1.0
    return rho


@dataclass(frozen=True)
class BSSRDFTable:
    """pbrt's five arrays (module docstring), float64; ``profile`` and ``profile_cdf`` are
    [n_rho, n_r]. Build with :meth:`from_profile`, which integrates as pbrt does."""

    rho_samples: np.ndarray
    radius_samples: np.ndarray
    profile: np.ndarray
    rho_eff: np.ndarray
    profile_cdf: np.ndarray

    @classmethod
    def from_profile(cls, rho_samples, radius_samples, profile) -> "BSSRDFTable":
        """rhoEff and profileCDF from the profile rows by Catmull-Rom integration (pbrt's
        ``IntegrateCatmullRom``)."""
        rho = np.asarray(rho_samples, dtype=np.float64)
        radius = np.asarray(radius_samples, dtype=np.float64)
        profile = np.asarray(profile, dtype=np.float64)
        if profile.shape != (len(rho), len(radius)):
            raise ValueError(f"profile has shape {profile.shape}, expected ({len(rho)}, {len(radius)})")
        rho_eff, cdf = integrate_catmull_rom(radius, profile)
        return cls(rho, radius, profile, rho_eff, cdf)

    def row(self, rho: float, array: np.ndarray | None = None) -> np.ndarray | None:
        """``array`` (default the profile; or profile_cdf, or rho_eff[:, None]) interpolated in
        rho with the Catmull-Rom weights, or None when rho is outside the albedo nodes."""
        w = catmull_rom_weights(self.rho_samples, rho)
        if w is None:
            return None
        offset, weights = w
        a = self.profile if array is None else array
        return sum(weights[k] * a[offset + k] for k in range(4) if weights[k] != 0.0)


def beam_diffusion_table(g: float, eta: float, n_rho: int = 100, n_r: int = 64) -> BSSRDFTable:
    """pbrt's own table (``ComputeBeamDiffusionBSSRDF``): photon beam diffusion at pbrt's nodes,
    profile = 2 pi r (Rd_ss + Rd_ms)(r) with sigma_s = rho, sigma_a = 1 - rho."""
    rho = pbrt_rho_samples(n_rho)
    radius = pbrt_radius_nodes(n_r)
    profile = np.zeros((n_rho, n_r))
    for i, a in enumerate(rho):
        if a > 0.0:  # rho = 0: no scattering, a zero row (as pbrt's formulas give)
            profile[i] = 2.0 * math.pi * radius * pbd_rd(radius, 1.0 - a, a, g, eta)
    return BSSRDFTable.from_profile(rho, radius, profile)


def _profile_at(table: BSSRDFTable, rho: float, r_optical) -> tuple[np.ndarray, np.ndarray | None]:
    row = table.row(rho)
    if row is None:
        return np.zeros_like(np.asarray(r_optical, dtype=np.float64)), None
    return catmull_rom(table.radius_samples, row, r_optical), row


def sr(table: BSSRDFTable, rho: float, r, sigma_t: float) -> np.ndarray:
    """``TabulatedBSSRDF::Sr`` for one channel: sigma_t^2 P(rho, r sigma_t) / (2 pi r sigma_t)
    [1/mm^2], elementwise in r [mm]; at r = 0 the profile is not divided (as pbrt); >= 0."""
    r_opt = np.asarray(r, dtype=np.float64) * sigma_t
    p, _ = _profile_at(table, rho, r_opt)
    with np.errstate(invalid="ignore", divide="ignore"):
        p = np.where(r_opt != 0.0, p / (2.0 * math.pi * r_opt), p)
    return np.maximum(0.0, p * sigma_t * sigma_t)


def pdf_sr(table: BSSRDFTable, rho: float, r, sigma_t: float) -> np.ndarray:
    """``TabulatedBSSRDF::Pdf_Sr``: :func:`sr` / rhoEff(rho), a density per unit area [1/mm^2]
    (so 2 pi r pdf_sr is the density of :func:`sample_sr` in r); 0 outside the nodes."""
    row_eff = table.row(rho, table.rho_eff[:, None])
    if row_eff is None:
        return np.zeros_like(np.asarray(r, dtype=np.float64))
    return sr(table, rho, r, sigma_t) / float(row_eff[0])


def sample_sr(table: BSSRDFTable, rho: float, u, sigma_t: float) -> np.ndarray:
    """``TabulatedBSSRDF::Sample_Sr``: radii [mm] drawn from the profile at rho, u uniform in
    [0, 1) (elementwise). As pbrt: -1 (no sample; pbrt-v3's -1, pbrt-v4's empty optional)
    where sigma_t = 0, and 0 where rho is outside the albedo nodes (``SampleCatmullRom2D``
    returns 0 when ``CatmullRomWeights`` fails)."""
    u = np.asarray(u, dtype=np.float64)
    if sigma_t == 0.0:
        return np.full(u.shape, -1.0)
    s = sample_catmull_rom_2d(table.rho_samples, table.radius_samples, table.profile, table.profile_cdf, rho, u)
    if s is None:
        return np.zeros(u.shape)
    return s[0] / sigma_t


def r_max(table: BSSRDFTable, rho: float, sigma_t: float, quantile: float = R_MAX_QUANTILE) -> float:
    """The radius holding ``quantile`` of the tabulated profile: pbrt's r_max = Sample_Sr(0.999)."""
    return float(sample_sr(table, rho, np.array([quantile]), sigma_t)[0])
