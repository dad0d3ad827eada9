"""The walk's bin lookup (torch): annular sectors on the surface, equal-solid-angle directions.

The layout of the bins is :class:`workers.fold.configs.BinLayout` (numpy).  Conventions in :mod:`workers.walk.conventions`.  A spatial bin is r in [r_lo, r_hi) x theta_s in
[lo, hi) with area A = (r_hi^2 - r_lo^2)/2 * dtheta_s; a directional bin is uniform in cos(theta_o)
over [0, 1] and in phi_o over the full turn, so every one has solid angle Omega = dcos * dphi =
2 pi / (n_cos * n_phi).  Both azimuths are binned centred on the plane of incidence
(:func:`azimuth_index`, edges :func:`schema.bins.azimuth_edges`): bin 0 = [-h/2, h/2), h = 2 pi / n.
The radial axis has one extra *overflow* index n_r for r >= r_max: it collects the flux beyond
the last edge so that Rd is the total diffuse reflectance.
"""

from __future__ import annotations

import math

import numpy as np
import torch

__all__ = [
    "wrap_angle", "uniform_index", "azimuth_index", "outgoing_azimuth", "sector_index", "outgoing_azimuth_index", "direction_index", "histogram_index", "exact_divmod",
]

TWO_PI = 2.0 * math.pi

# Angles within this many radians below 2 pi are taken as 0: at normal incidence a photon
# scattered once leaves exactly radially (phi_o = 0), and float rounding of atan2 may put it a few
# ulp below zero; the snap reports such an exit as phi_o = 0 rather than 2 pi - ulp.  Binning does
# not depend on it: both lie in the middle of the centred bin 0 (:func:`azimuth_index`).
_WRAP_SNAP = 1e-5


def wrap_angle(a: torch.Tensor) -> torch.Tensor:
    """Wrap radians into [0, 2 pi), snapping values within 1e-5 below 2 pi to 0 (see _WRAP_SNAP)."""
    a = torch.remainder(a, TWO_PI)
    return torch.where(a >= TWO_PI - _WRAP_SNAP, torch.zeros_like(a), a)


def _uniform_edges(lo: float, hi: float, count: int) -> torch.Tensor:
    # The same construction as schema.uniform_edges, so the lookups match the tables' edges.
    edges = np.linspace(lo, hi, count + 1, dtype=np.float64)
    edges[0], edges[-1] = lo, hi
    return torch.from_numpy(edges)


def uniform_index(value: torch.Tensor, lo: float, hi: float, count: int) -> torch.Tensor:
    """Index of value in `count` equal bins [lo + k h, lo + (k+1) h) over [lo, hi], int64.

    floor((v - lo) / h) may land one bin off the stored edges (schema.uniform_edges) when v is on
    or within rounding of an edge, so the guess is corrected against those edges: the result is
    the bin [edges[k], edges[k+1]) that holds v, as a search of the edges gives, without one
    (torch.bucketize does not fuse into compiled kernels).  Out-of-range values are clamped into
    the end bins; the closed upper end belongs to the last bin.
    """
    edge = _edge_function(float(lo), float(hi), int(count), value.dtype)
    k = torch.clamp(torch.floor((value - lo) * (count / (hi - lo))).to(torch.int64), 0, count - 1)
    k = torch.where((value < edge(k)) & (k > 0), k - 1, k)
    k = torch.where((value >= edge(k + 1)) & (k < count - 1), k + 1, k)
    return k


def _edge_function(lo: float, hi: float, count: int, dtype: torch.dtype):
    """k -> edges[k] of :func:`_uniform_edges` (in dtype) for an index tensor k in [0, count].

    From lo = 0 (every axis of the tables) the edges are computed, not looked up: numpy's
    linspace forms edge k < count as k * step, step = (hi - lo) / count, in float64 (plus lo = 0,
    which changes nothing), and sets the last edge to hi; the same float64 product here gives the
    same value (tested), and a compiled kernel needs no gather.  Otherwise: a table lookup.
    """
    if lo == 0.0:
        step = (hi - lo) / count

        def edge(k: torch.Tensor) -> torch.Tensor:
            return torch.where(k >= count, hi, k.to(torch.float64) * step).to(dtype)

        return edge
    edges = _uniform_edges(lo, hi, count).to(dtype)
    return lambda k: edges[k]


def azimuth_index(a: torch.Tensor, count: int) -> torch.Tensor:
    """Bin of the azimuth a [rad, any real] among ``count`` bins centred on 0, int64:

        k = floor(((a + h/2) mod 2 pi) / h),   h = 2 pi / count,

    i.e. bin k = [(k - 1/2) h, (k + 1/2) h) modulo 2 pi, bin 0 = [-h/2, h/2) (edges
    :func:`schema.bins.azimuth_edges`).  Computed as :func:`uniform_index` of the shifted angle
    over [0, 2 pi), so exact against uniform_edges(0, 2 pi, count) and, up to the rounding of
    the half-bin shift, against the stored edges.  The mirror -a of an angle inside bin k is
    inside bin (count - k) mod count.  A shifted angle that rounds up to 2 pi (a a few ulp below
    -h/2) is in the last bin, as it should be.
    """
    half = math.pi / count
    return uniform_index(torch.remainder(a + half, TWO_PI), 0.0, TWO_PI, count)


def outgoing_azimuth(px: torch.Tensor, py: torch.Tensor, tx: torch.Tensor, ty: torch.Tensor) -> torch.Tensor:
    """phi_o in [0, 2 pi): azimuth of the horizontal direction (tx, ty) from the radial (px, py).

    Computed as atan2(p x t, p . t) so it is exact for parallel vectors; at r = 0 the radial
    direction is +x by convention, and a direction with no horizontal part has phi_o = 0 (atan2
    of signed zeros would give 0 or pi by the signs).  The walk bins phi_o with
    :func:`outgoing_azimuth_index`, without the angle.
    """
    cross, dot = _from_radial(px, py, tx, ty)
    return torch.where((cross == 0) & (dot == 0), 0.0, wrap_angle(torch.atan2(cross, dot)))


def _from_radial(px: torch.Tensor, py: torch.Tensor, tx: torch.Tensor, ty: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(p x t, p . t): the horizontal direction t in the frame of the radial direction p, which
    is +x at r = 0 (x along p, y counterclockwise from it; not normalised)."""
    at_origin = (px == 0) & (py == 0)
    px = torch.where(at_origin, torch.ones_like(px), px)
    return px * ty - py * tx, px * tx + py * ty


SECTOR_MAX = 16
"""Up to this many azimuth bins, :func:`sector_index` decides a direction's bin by one cross
product per bin edge; beyond, by atan2 and :func:`azimuth_index`."""


def sector_index(y: torch.Tensor, x: torch.Tensor, count: int) -> torch.Tensor:
    """Bin of the direction (x, y) among ``count`` azimuth bins centred on 0, int64: the bin
    :func:`azimuth_index` gives for atan2(y, x), decided without the angle.

    Edge j = 1 .. count of the bins is the direction e_j at (j - 1/2) h, h = 2 pi / count.
    For (x, y) at an angle a in [0, pi) (y > 0, or y = 0 and x > 0) the bin is the number of
    edges in (0, pi) with e_j x (x, y) >= 0 (a at or past e_j); for a in [pi, 2 pi) it is the
    number of edges in (0, pi) plus the number of the others that a is at or past, a count of
    ``count`` being bin 0.  Within a half turn the sign of the cross product orders the angles,
    so this is the half-open [lo, hi) lookup of the exact angle against the edge directions,
    rounded once (the product), where atan2 rounds the angle and the half-bin shift rounds
    again: the two agree but within rounding of an edge (tested).  The zero vector is in bin 0
    (its angle is taken as 0).  For count <= SECTOR_MAX every edge is a constant of the kernel,
    with no transcendental function, no gather and no float-to-integer conversion; above it
    the atan2 lookup is used.
    """
    if count == 1:
        return torch.zeros_like(x, dtype=torch.int64)
    if count > SECTOR_MAX:
        at_zero = (x == 0) & (y == 0)
        return torch.where(at_zero, 0, azimuth_index(torch.atan2(y, x), count))
    h = TWO_PI / count
    upper_edges = [j for j in range(1, count + 1) if (j - 0.5) * h < math.pi]
    lower_edges = [j for j in range(1, count + 1) if (j - 0.5) * h >= math.pi]

    def passed(edges: list[int]) -> torch.Tensor:
        n = torch.zeros_like(x, dtype=torch.int64)
        for j in edges:
            c, s = math.cos((j - 0.5) * h), math.sin((j - 0.5) * h)
            n = n + (c * y - s * x >= 0).to(torch.int64)
        return n

    upper = (y > 0) | ((y == 0) & (x > 0))
    lower = len(upper_edges) + passed(lower_edges)
    k = torch.where(upper, passed(upper_edges), torch.where(lower >= count, 0, lower))
    return torch.where((x == 0) & (y == 0), 0, k)


def outgoing_azimuth_index(px: torch.Tensor, py: torch.Tensor, tx: torch.Tensor, ty: torch.Tensor, count: int) -> torch.Tensor:
    """Bin among ``count`` of phi_o, the azimuth of the horizontal direction (tx, ty) from the
    radial direction (px, py) (+x at r = 0), as :func:`outgoing_azimuth` measures it:
    :func:`sector_index` of the vector (x, y) = (p . t, p x t).  A direction with no horizontal
    part is in bin 0."""
    cross, dot = _from_radial(px, py, tx, ty)
    return sector_index(cross, dot, count)


def direction_index(cos_o: torch.Tensor, px: torch.Tensor, py: torch.Tensor, tx: torch.Tensor, ty: torch.Tensor,
                    n_cos: int, n_phi: int) -> torch.Tensor:
    """Direction bin cos * n_phi + phi (int64) of a direction leaving at (px, py) with outgoing
    cosine cos_o and horizontal part (tx, ty): the exit tally, the hybrid and the connections
    all bin directions with it."""
    return uniform_index(cos_o, 0.0, 1.0, n_cos) * n_phi + outgoing_azimuth_index(px, py, tx, ty, n_phi)


def histogram_index(cfg, comp, spatial, direction, n_sp: int, n_dir: int, n_comp: int = 2):
    """Index into a flattened [configuration, component, spatial, direction] histogram.

    spatial = ir * n_theta + it among n_sp = (n_r + 1) n_theta bins (overflow included),
    direction = ic * n_phi + ip among n_dir = n_cos n_phi; n_comp components (single and
    multiple, or with the total: 3).  Integer tensors or ints; the exit tally, the hybrid and the
    shard run's connections all index their histograms with it.
    """
    return ((cfg * n_comp + comp) * n_sp + spatial) * n_dir + direction


def exact_divmod(a: torch.Tensor, n) -> tuple[torch.Tensor, torch.Tensor]:
    """(a // n, a % n) of a non-negative int64 tensor a by a positive divisor n (an int or an int64
    tensor), both below 2**50, through float64.

    Why: x86 has no vector integer division, so inside a compiled kernel inductor divides int64
    lane by lane with a scalar idiv (~10-40 cycles each, by core) where a float64 division is
    one vector instruction.  Exact: with a = q n + r, 0 <= r < n, (a + 0.5) / n = q + (r + 0.5) / n
    lies at least 0.5 / n from an integer; a + 0.5 is exact in float64 and the quotient's rounding
    error, at most (q + 1) 2**-53, stays below 0.5 / n while (q + 1) n <= a + n < 2**51, so the
    floor is q (tests/workers/test_binning.py checks it next to every multiple).  An int divisor of
    1 (one theta_s bin, one configuration) needs no division at all."""
    if isinstance(n, int) and n == 1:
        return a, torch.zeros_like(a)
    q = torch.floor((a.to(torch.float64) + 0.5) / n).to(torch.int64)
    return q, a - q * n
