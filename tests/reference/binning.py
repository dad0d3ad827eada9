"""Searched bin lookups: the plain reference the walk's fused lookups are tested against.

The walk bins events with computed uniform edges (:func:`workers.walk.binning.uniform_index`) and a
bucket index or binary search of the radial edges (:mod:`workers.walk.search`); these look the values up in the
stored float64 edges with torch.searchsorted / bucketize, the obvious way, for the tests only.
"""

from __future__ import annotations

from dataclasses import dataclass

import math

import torch

from workers.fold.configs import BinLayout

__all__ = ["edge_index", "azimuth_edge_index", "SearchedLookup", "searched"]


def edge_index(value: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """Index k of the bin [edges[k], edges[k+1]) holding value, int64, clamped to the end bins.

    A value exactly on edge k is in bin k; the closed upper end (value == edges[-1], e.g.
    cos = 1) belongs to the last bin.
    """
    idx = torch.bucketize(value.contiguous(), edges.to(value.dtype), right=True) - 1
    return torch.clamp(idx, 0, len(edges) - 2)


def azimuth_edge_index(angle: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """Bin of an azimuth (any real, radians) among edges spanning one full turn from edges[0]:
    an angle outside [edges[0], edges[0] + 2 pi) is taken modulo 2 pi into it (one inside is
    searched as it is, so the stored edges themselves are exact), then searched."""
    lo = float(edges[0])
    inside = (angle >= lo) & (angle < lo + 2.0 * math.pi)
    wrapped = torch.where(inside, angle, lo + torch.remainder(angle - lo, 2.0 * math.pi))
    return edge_index(wrapped, edges)


@dataclass(frozen=True)
class SearchedLookup:
    """Bins of a :class:`workers.walk.binning.BinLayout` by searching its stored edges."""

    layout: BinLayout

    def radial_index(self, r_mm: torch.Tensor, channel: torch.Tensor) -> torch.Tensor:
        """Radial bin of r (mm) for each event's channel; n_r for r >= r_max (overflow)."""
        edges = torch.as_tensor(self.layout.radial_mm, dtype=r_mm.dtype)
        # searchsorted(right) - 1 puts r in [edge_k, edge_k+1) into k; r >= r_max gives n_r.
        idx = torch.searchsorted(edges[channel], r_mm.unsqueeze(-1), right=True).squeeze(-1) - 1
        return torch.clamp(idx, 0, self.layout.n_r)

    def theta_index(self, theta_s: torch.Tensor) -> torch.Tensor:
        """theta_s bin of an angle (any real: taken modulo 2 pi into the edges' turn)."""
        return azimuth_edge_index(theta_s, torch.from_numpy(self.layout.theta_s))

    def cos_index(self, cos_o: torch.Tensor) -> torch.Tensor:
        return edge_index(cos_o, torch.from_numpy(self.layout.cos_o))

    def phi_index(self, phi_o: torch.Tensor) -> torch.Tensor:
        """phi_o bin of an angle (any real: taken modulo 2 pi into the edges' turn)."""
        return azimuth_edge_index(phi_o, torch.from_numpy(self.layout.phi_o))


def searched(layout: BinLayout) -> SearchedLookup:
    return SearchedLookup(layout)
