"""Bin layout of the tallies (docs/architecture.md, "Physics conventions").

A spatial bin is an annular sector of the surface z = 0 around the entry point:
r in [r_lo, r_hi) [mm] x theta_s in [theta_lo, theta_hi) [rad], theta_s measured from +x (the
incidence plane, forward). A directional bin is uniform in cos(theta_o) over [0, 1] (theta_o from
the outward normal +z) and in phi_o (from the outward radial direction at the exit point). Every
bin is half-open [lo, hi).

Both azimuths are binned *centred on the plane of incidence*: with n bins of width h = 2 pi / n,
bin k is [(k - 1/2) h, (k + 1/2) h) taken modulo 2 pi, so bin 0 = [-h/2, h/2) holds theta_s = 0
(forward, +x) and phi_o = 0 (leaving radially), and the stored edges run from -h/2 to
2 pi - h/2 (:func:`azimuth_edges`).  The problem is mirror-symmetric about the plane of
incidence (y -> -y maps theta_s -> -theta_s and phi_o -> -phi_o), and with these bins the
mirror of bin k is bin (n - k) mod n, a bin of the table: single scattering at normal incidence,
which leaves exactly at phi_o = 0, falls in the middle of bin 0 instead of on its edge.

Defaults: 48 log-spaced radial bins out to 16 transport mean free paths (per channel), first
inner edge at 1e-3 of the maximum; theta_s "auto" (1 bin at normal incidence, 12 otherwise);
8 bins in cos(theta_o); 8 bins in phi_o.

Radial spacing "pbrt" puts one bin on each radius node of pbrt's tabulated BSSRDF (pbrt-v3
``ComputeBeamDiffusionBSSRDF``): nodes r_0 = 0, r_1 = 2.5e-3, r_j = 1.2 r_{j-1} in optical radii
r sigma_t; bin j >= 1 is [r_j / sqrt(1.2), r_j sqrt(1.2)), centred on r_j in log r, and bin 0 is
[0, r_1 / sqrt(1.2)). The extent is fixed by ``count`` (64 nodes: out to 222 optical radii).
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator
from pydantic_core import PydanticCustomError

from .constraints import Interval

__all__ = [
    "RadialBins",
    "ThetaSBins",
    "CosThetaOBins",
    "PhiOBins",
    "BinSpec",
    "channel_radial_edges_mm",
    "theta_s_count",
    "radial_edges",
    "uniform_edges",
    "azimuth_edges",
    "MAX_TOTAL_BINS",
    "DEFAULT_MAX_MFP",
    "THETA_S_AUTO_OBLIQUE",
    "TWO_PI",
    "PBRT_R1",
    "PBRT_RATIO",
    "pbrt_radius_nodes",
    "pbrt_radial_edges",
    "MAX_MFP_RANGE",
    "MAX_MM_RANGE",
    "MIN_FRACTION_RANGE",
    "PBRT_MAX_COUNT",
]

TWO_PI = 2.0 * math.pi

MAX_TOTAL_BINS = 2**24
"""Limit on n_r * n_theta_s * n_cos * n_phi * n_channels * n_incidence (memory of the tallies)."""

DEFAULT_MAX_MFP = 16.0
"""Default radial extent, in transport mean free paths 1 / sigma_t'."""

THETA_S_AUTO_OBLIQUE = 12
"""theta_s bin count chosen by "auto" when some incidence angle is not 0."""

PBRT_R1 = 2.5e-3
"""pbrt's first non-zero radius node, in optical radii r sigma_t (pbrt-v3 bssrdf.cpp)."""
PBRT_RATIO = 1.2
"""Ratio of consecutive non-zero radius nodes of pbrt's table."""

# Physical ranges of the radial extent (docs/architecture.md, "Physical ranges"): with a medium
# inside schema.medium's ranges every edge is a finite, normal float64 in mm, and in optical radii
# a finite float32 (the walk's lookups), and 1 / area and its square are finite.
MAX_MFP_RANGE = Interval(0.001, 10_000.0, what="max_mfp")
"""Outer radius in transport mean free paths: at 1e4 nothing of a path capped at max_scatter
(<= 1e7 events, a diffusion length of a few thousand) reaches it; below 1e-3 a bin is a point."""
MAX_MM_RANGE = Interval(1e-6, 1e6, what="max_mm")
"""Outer radius in mm: 1 nm to 1 km, the lengths of schema.medium's mean free paths."""
MIN_FRACTION_RANGE = Interval(1e-9, 1.0, hi_open=True, what="min_fraction")
"""First inner edge of log spacing as a fraction of the outer radius: nine decades of r."""
PBRT_MAX_COUNT = 100
"""Most pbrt radius nodes: node 99 is 2.5e-3 * 1.2^98 = 1.5e5 optical radii (pbrt uses 64); at
4096 nodes 1.2^4094 overflows float64."""

_CONFIG = ConfigDict(frozen=True, extra="forbid")


class RadialBins(BaseModel):
    """Radial bins r in [r_lo, r_hi) [mm], ``count`` of them from 0 to the maximum radius.

    The maximum is either ``max_mm`` (same for every channel) or ``max_mfp`` transport mean free
    paths 1 / sigma_t' (per channel); exactly one, default ``max_mfp = 16``.
    ``spacing = "log"`` (default): edges [0, r_min, r_min q, ..., r_max], geometric from
    r_min = ``min_fraction`` * r_max to r_max, ``count`` bins in total including [0, r_min).
    ``spacing = "linear"``: ``count`` equal bins (``min_fraction`` unused). ``count = 1`` is the
    single bin [0, r_max).
    ``spacing = "pbrt"``: one bin per radius node of pbrt's table, in optical radii (see the
    module docstring); ``count`` >= 2 nodes, no ``max_mm`` / ``max_mfp`` (the nodes fix the
    extent), ``min_fraction`` unused.
    """

    model_config = _CONFIG

    count: Annotated[int, Interval(1, 4096, what="radial bin count")] = 48
    max_mm: Annotated[float, MAX_MM_RANGE] | None = Field(
        None, description=f"Outer radius in mm, in {MAX_MM_RANGE} (excludes max_mfp)."
    )
    max_mfp: Annotated[float, MAX_MFP_RANGE] | None = Field(
        None, description=f"Outer radius in transport mean free paths 1/sigma_t' (per channel), in {MAX_MFP_RANGE}; "
        "default 16 when max_mm is not given."
    )
    spacing: Literal["linear", "log", "pbrt"] = "log"
    min_fraction: Annotated[float, MIN_FRACTION_RANGE] = Field(
        1e-3, description=f"Log spacing: first inner edge as a fraction of the maximum, in {MIN_FRACTION_RANGE}.")

    @model_validator(mode="before")
    @classmethod
    def _default_extent(cls, data: Any) -> Any:
        """Fill ``max_mfp = 16`` when neither extent is given."""
        if isinstance(data, dict) and data.get("max_mm") is None and data.get("max_mfp") is None:
            if data.get("spacing") != "pbrt":  # pbrt's nodes fix the extent themselves
                data = {**data, "max_mfp": DEFAULT_MAX_MFP}
        return data

    @model_validator(mode="after")
    def _pbrt_nodes(self) -> RadialBins:
        """Spacing "pbrt": at least 2 nodes, and no extent of its own."""
        if self.spacing != "pbrt":
            return self
        if self.max_mm is not None or self.max_mfp is not None:
            raise PydanticCustomError(
                "radial_extent",
                'spacing "pbrt" puts bins on pbrt\'s radius nodes, whose extent is fixed by count '
                "(optical radii up to 2.5e-3 * 1.2^(count - 1.5)); remove max_mm / max_mfp; "
                "received max_mm={mm}, max_mfp={mfp}",
                {"mm": self.max_mm, "mfp": self.max_mfp},
            )
        if not 2 <= self.count <= PBRT_MAX_COUNT:
            raise PydanticCustomError(
                "radial_count",
                'spacing "pbrt" needs count in the allowed range [2, {hi}] (pbrt uses 64; node k is '
                "2.5e-3 * 1.2^(k - 1) optical radii); received {n}",
                {"n": self.count, "hi": PBRT_MAX_COUNT},
            )
        return self

    @model_validator(mode="after")
    def _one_extent(self) -> RadialBins:
        if self.max_mm is not None and self.max_mfp is not None:
            raise PydanticCustomError(
                "radial_extent",
                "give exactly one of max_mm or max_mfp; received max_mm={mm}, max_mfp={mfp}",
                {"mm": self.max_mm, "mfp": self.max_mfp},
            )
        return self

    def max_radius_mm(self, transport_mfp_mm: float) -> float:
        """Outer radius [mm] for a channel whose transport mean free path is given [mm]
        (not for spacing "pbrt", whose edges are :func:`pbrt_radial_edges` / sigma_t)."""
        if self.spacing == "pbrt":
            raise ValueError('spacing "pbrt" has no max radius of its own: use pbrt_radial_edges(count) / sigma_t')
        return self.max_mm if self.max_mm is not None else self.max_mfp * transport_mfp_mm


class ThetaSBins(BaseModel):
    """Bins of the exit azimuth theta_s from +x, centred on it: bin k = [(k - 1/2) h, (k + 1/2) h),
    h = 2 pi / count (module docstring). ``count`` 1..360 or ``None`` ("auto": 1 if every
    incidence angle is 0, where the BSSRDF is symmetric, else 12)."""

    model_config = _CONFIG

    count: Annotated[int, Interval(1, 360, what="theta_s bin count")] | None = None


class CosThetaOBins(BaseModel):
    """Bins uniform in cos(theta_o) over [0, 1]; ``count`` 1..256, default 8."""

    model_config = _CONFIG

    count: Annotated[int, Interval(1, 256, what="cos_theta_o bin count")] = 8


class PhiOBins(BaseModel):
    """Bins uniform in phi_o, from the outward radial direction, centred on it: bin k =
    [(k - 1/2) h, (k + 1/2) h), h = 2 pi / count (module docstring); ``count`` 1..360, default 8."""

    model_config = _CONFIG

    count: Annotated[int, Interval(1, 360, what="phi_o bin count")] = 8


class BinSpec(BaseModel):
    """The whole bin layout; every part has defaults (see the module docstring)."""

    model_config = _CONFIG

    radial: RadialBins = Field(default_factory=RadialBins)
    theta_s: ThetaSBins = Field(default_factory=ThetaSBins)
    cos_theta_o: CosThetaOBins = Field(default_factory=CosThetaOBins)
    phi_o: PhiOBins = Field(default_factory=PhiOBins)


def uniform_edges(lo: float, hi: float, count: int) -> np.ndarray:
    """``count + 1`` equally spaced float64 edges from ``lo`` to ``hi`` (both exact)."""
    edges = np.linspace(lo, hi, count + 1, dtype=np.float64)
    edges[0], edges[-1] = lo, hi
    return edges


def azimuth_edges(count: int) -> np.ndarray:
    """``count + 1`` edges [rad] of azimuth bins centred on 0: uniform_edges(0, 2 pi, count) - h/2,
    h = 2 pi / count, i.e. from -h/2 to 2 pi - h/2; bin 0 = [-h/2, h/2).  An angle a belongs to
    the bin k whose [edges[k], edges[k+1]) holds a taken modulo 2 pi into [-h/2, 2 pi - h/2)."""
    return uniform_edges(0.0, TWO_PI, count) - math.pi / count


def radial_edges(radial: RadialBins, r_max_mm: float) -> np.ndarray:
    """``radial.count + 1`` strictly increasing radial edges [mm] from 0 to ``r_max_mm``."""
    n = radial.count
    if n == 1:
        return np.array([0.0, r_max_mm], dtype=np.float64)
    if radial.spacing == "linear":
        return uniform_edges(0.0, r_max_mm, n)
    r_min = radial.min_fraction * r_max_mm
    # geomspace gives n points r_min..r_max, i.e. n - 1 geometric bins, plus the bin [0, r_min).
    outer = np.geomspace(r_min, r_max_mm, n, dtype=np.float64)
    outer[0], outer[-1] = r_min, r_max_mm
    return np.concatenate([[0.0], outer])



def pbrt_radius_nodes(count: int) -> np.ndarray:
    """pbrt's radius nodes in optical radii: r_0 = 0, r_j = 2.5e-3 * 1.2^(j - 1), ``count`` of them."""
    if count < 2:
        raise ValueError(f"pbrt's radius nodes need count >= 2; received {count}")
    return np.concatenate([[0.0], PBRT_R1 * PBRT_RATIO ** np.arange(count - 1, dtype=np.float64)])


def pbrt_radial_edges(count: int) -> np.ndarray:
    """``count + 1`` edges in optical radii with one bin per node of :func:`pbrt_radius_nodes`:
    [0, r_1 / sqrt(1.2), r_1 sqrt(1.2), r_2 sqrt(1.2), ...], bin j >= 1 centred on r_j in log r."""
    nodes = pbrt_radius_nodes(count)
    half = math.sqrt(PBRT_RATIO)
    return np.concatenate([[0.0, nodes[1] / half], nodes[1:] * half])


def channel_radial_edges_mm(bins: BinSpec, channels) -> np.ndarray:
    """Radial edges [mm] of each channel (anything with ``sigma_t`` and ``transport_mfp_mm``),
    float64 [n_channels, n_r + 1]; column 0 is 0."""
    r = bins.radial
    if r.spacing == "pbrt":  # pbrt's nodes are optical radii r sigma_t: per channel in mm
        return np.stack([pbrt_radial_edges(r.count) / c.sigma_t for c in channels])
    return np.stack([radial_edges(r, r.max_radius_mm(c.transport_mfp_mm)) for c in channels])


def theta_s_count(bins: BinSpec, incidence_deg) -> int:
    """theta_s bin count, "auto" resolved: 1 if every incidence angle is 0, else THETA_S_AUTO_OBLIQUE."""
    if bins.theta_s.count is not None:
        return bins.theta_s.count
    return 1 if all(t == 0.0 for t in incidence_deg) else THETA_S_AUTO_OBLIQUE
