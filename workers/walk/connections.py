"""The connection estimator (next-event connections to the surface) with multiple importance sampling.

At a scattering vertex x_p reached with weight w travelling along w_p, the flux that leaves
through a surface element dA at x_o after this one scattering and no other is

    f(x_o) dA = w * albedo * p(w_p . w21) * exp(-d) * T21(cos_in) * cos_in / d^2 * dA

(optical units, d = |x_o - x_p|, w21 = (x_o - x_p)/d, cos_in = w21 . n, T21 = 1 - Fr(cos_in,
1/eta), zero under total internal reflection).  Two techniques sample x_o:

- *uniform*: for every spatial bin, x_o uniform in (r, theta_s) of the bin (theta_s bins centred
  on +x, workers.walk.conventions), density per area q_u = 1 / (r dr dtheta_s);
- *phase*: the direction the walk samples from the phase function at this vertex, followed to the
  surface, density per area q_p = p(w_p . w21) cos_in / d^2 (zero if it heads down).

Each sample contributes f / (q_u + q_p) to G of its spatial bin and of the bin of its refracted
direction (balance heuristic, one sample per technique).  Since f / q_p = w albedo exp(-d) T21,
every contribution is bounded by w * albedo: the estimator has finite variance, unlike uniform
sampling alone (whose integrand grows like |z|/d^3 under a shallow vertex).  Outside the last
radial edge only the phase technique samples, giving the flux beyond r_max.  S gets the same
with T cos_in / cos_o in place of T cos_in (:func:`workers.walk.optics.transmittance_cos_ratio`:
bounded, and exactly 1 at eta = 1), divided by A Omega when results are formed; S = G / cos_o
with a float cos_o that rounds to 0 at grazing angles blew up to 1e17-1e24 at eta = 1.  Vertices after the first scattering contribute to
``multiple``, the first to ``single``.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from functools import lru_cache
from typing import Iterator

import torch

from .binning import TWO_PI, direction_index, sector_index
from .conventions import PURPOSE_CONNECT
from .kernels import compile_kernel
from .optics import fresnel_transmittance, refracted_cos, transmittance_cos_ratio
from .phase import DEFAULT_PHASE, phase_function
from .rng import philox4x32, photon_words, uniform_halfopen
from .walk import ConfigTable

__all__ = ["ConnectionGeometry", "Vertices", "VertexBuffer", "connect_uniform", "connect_phase", "connection_function"]


@dataclass(frozen=True)
class Vertices:
    """Scattering vertices of the walk, structure of arrays (one tensor per field, length V).

    x, y, z: float32 optical position x_p; ux, uy, uz: unit direction of travel arriving (w_p);
    vx, vy, vz: the direction leaving, the walk's own phase-function sample there; w: weight
    arriving; cfg, photon: int64 configuration and photon index; draw: int32 Philox draw index of
    the step that reached the vertex; multiple: int64 1 after two or more scatterings (component
    ``multiple``), 0 at the first vertex (``single``).
    """

    x: torch.Tensor
    y: torch.Tensor
    z: torch.Tensor
    ux: torch.Tensor
    uy: torch.Tensor
    uz: torch.Tensor
    vx: torch.Tensor
    vy: torch.Tensor
    vz: torch.Tensor
    w: torch.Tensor
    cfg: torch.Tensor
    photon: torch.Tensor
    draw: torch.Tensor
    multiple: torch.Tensor

    def __len__(self) -> int:
        return len(self.x)

    def _map(self, fn) -> "Vertices":
        return Vertices(*(fn(getattr(self, f.name)) for f in fields(self)))

    @classmethod
    def cat(cls, parts: list["Vertices"]) -> "Vertices":
        """The vertices of parts, one after another."""
        return cls(*(torch.cat([getattr(p, f.name) for p in parts]) for f in fields(cls)))

    def slice(self, start: int, stop: int | None = None) -> "Vertices":
        """Vertices [start, stop)."""
        return self._map(lambda t: t[start:stop])

    def pad(self, n: int) -> "Vertices":
        """At least n vertices: copies of the first one appended (for a kernel of static shape)."""
        if len(self) >= n:
            return self
        return self._map(lambda t: torch.cat((t, t[:1].expand(n - len(t), *t.shape[1:]))))


class VertexBuffer:
    """Vertices collected from the walk until a chunk of `chunk` vertices is full."""

    def __init__(self, chunk: int):
        self.chunk = chunk
        self.parts: list[Vertices] = []
        self.count = 0

    def add(self, v: Vertices) -> bool:
        """Keep v; returns whether a full chunk is waiting."""
        self.parts.append(v)
        self.count += len(v)
        return self.count >= self.chunk

    def chunks(self, force: bool) -> Iterator[Vertices]:
        """The collected vertices in chunks of `chunk`, in order; a short last chunk only if
        force (else it stays in the buffer)."""
        if not self.parts:
            return
        v = Vertices.cat(self.parts)
        self.parts, self.count = [], 0
        for a in range(0, len(v), self.chunk):
            b = min(len(v), a + self.chunk)
            if b - a < self.chunk and not force:
                self.parts, self.count = [v.slice(a)], len(v) - a
                return
            yield v.slice(a, b)

@dataclass(frozen=True)
class ConnectionGeometry:
    """Bin edges in optical units per configuration, as tensors for the kernels.

    r_lo, r_hi: float32 [n_cfg, n_r]; n_theta, n_cos, n_phi: counts; eta: relative index.
    """

    r_lo: torch.Tensor
    r_hi: torch.Tensor
    n_theta: int
    n_cos: int
    n_phi: int
    eta: float
    phase: str = DEFAULT_PHASE  # the phase function (workers.walk.phase)

    @property
    def n_r(self) -> int:
        return self.r_lo.shape[1]


def _direction_bin(xo, yo, dx, dy, cos_in, geo: ConnectionGeometry):
    """Direction bin cos * n_phi + phi of the direction refracted out at x_o."""
    return direction_index(refracted_cos(cos_in, 1.0 / geo.eta), xo, yo, dx, dy, geo.n_cos, geo.n_phi)


def connect_uniform(v: Vertices, table: ConfigTable, geo: ConnectionGeometry):
    """Uniform-technique samples of every spatial bin for a chunk of V vertices.

    Each vertex draws from its photon's stream (Philox counter words: the photon index and the
    vertex's draw; key: its configuration's, as in the walk); albedo and g are its
    configuration's.  Returns (G, S, spatial, direction) of shape [V, n_r * n_theta]: the
    MIS-weighted contribution to G, G / cos_o, the spatial bin index (r * n_theta + theta) and
    the direction bin index.
    """
    albedo, g, cfg = table.albedo[v.cfg], table.g[v.cfg], v.cfg
    c_lo, c_hi = photon_words(v.photon)
    draw, k0, k1 = v.draw, table.k0[cfg], table.k1[cfg]
    n_r, n_t = geo.n_r, geo.n_theta
    n_bins = n_r * n_t
    n_pairs = (n_bins + 1) // 2
    # Two bins per Philox block: (u_r, u_theta) for bin 2j from words 0, 1 and for 2j+1 from 2, 3.
    c3 = torch.arange(n_pairs, dtype=torch.int32) + PURPOSE_CONNECT
    b = philox4x32(c_lo[:, None], c_hi[:, None], draw[:, None], c3[None, :], k0[:, None], k1[:, None])
    u_r = torch.stack((b[0], b[2]), dim=-1).reshape(-1, 2 * n_pairs)[:, :n_bins]
    u_t = torch.stack((b[1], b[3]), dim=-1).reshape(-1, 2 * n_pairs)[:, :n_bins]
    u_r, u_t = uniform_halfopen(u_r), uniform_halfopen(u_t)

    r_lo = geo.r_lo[cfg].repeat_interleave(n_t, dim=1)  # [V, n_bins], bin = ir * n_t + it
    dr = geo.r_hi[cfg].repeat_interleave(n_t, dim=1) - r_lo
    dtheta = TWO_PI / n_t
    # theta_s bin k is [(k - 1/2) h, (k + 1/2) h), centred on +x (workers.walk.conventions).
    theta_lo = ((torch.arange(n_bins) % n_t).to(torch.float32) - 0.5) * dtheta
    r = r_lo + u_r * dr
    theta = theta_lo[None, :] + u_t * dtheta
    xo, yo = r * torch.cos(theta), r * torch.sin(theta)

    dx, dy = xo - v.x[:, None], yo - v.y[:, None]
    dz = -v.z[:, None]  # vertex below the surface: dz > 0
    d2 = dx * dx + dy * dy + dz * dz
    d = torch.sqrt(d2)
    cos_in = dz / d
    mu = (v.ux[:, None] * dx + v.uy[:, None] * dy + v.uz[:, None] * dz) / d
    q_p = phase_function(geo.phase).pdf(mu, g[:, None]) * cos_in / d2
    # q_u = 1/(r dr dtheta) is infinite at r = 0: the clamp makes its MIS weight exactly 0 there.
    q_u = 1.0 / torch.clamp(r * dr * dtheta, min=1e-30)
    # f / (q_u + q_p) to G; to S the same with T cos_in / cos_o for T cos_in (bounded, exactly 1
    # at eta = 1 however grazing: no division by a cos_o that rounds to 0).
    base = (v.w * albedo)[:, None] * torch.exp(-d) / (q_p + q_u)
    G = base * fresnel_transmittance(cos_in, 1.0 / geo.eta) * q_p
    S = base * transmittance_cos_ratio(cos_in, 1.0 / geo.eta) * (phase_function(geo.phase).evaluate(mu, g[:, None]) / d2)
    direction = _direction_bin(xo, yo, dx, dy, cos_in, geo)
    spatial = torch.arange(n_bins, dtype=torch.int64)[None, :].expand_as(direction)
    return G, S, spatial, direction


def connect_phase(v: Vertices, table: ConfigTable, geo: ConnectionGeometry):
    """Phase-technique sample: the walk's own scattering direction (vx, vy, vz) at each of V
    vertices.

    Returns (G, S, spatial, direction) of shape [V]; spatial = r * n_theta + theta, or
    n_r * n_theta + theta beyond r_max (the overflow ring, where q_u = 0).  G = 0 where v
    points into the medium.
    """
    albedo, g, cfg, w = table.albedo[v.cfg], table.g[v.cfg], v.cfg, v.w
    vx, vy, vz = v.vx, v.vy, v.vz
    n_t = geo.n_theta
    up = vz > 0
    t = -v.z / torch.clamp(vz, min=1e-30)
    xo, yo = v.x + t * vx, v.y + t * vy
    r = torch.sqrt(xo * xo + yo * yo)
    edges_hi = geo.r_hi[cfg]  # [V, n_r]
    ir = (r[:, None] >= edges_hi).sum(dim=1)  # bins are [lo, hi): count edges at or below r
    inside = ir < geo.n_r
    ir_c = torch.clamp(ir, max=geo.n_r - 1)
    r_lo = geo.r_lo[cfg].gather(1, ir_c[:, None])[:, 0]
    dr = edges_hi.gather(1, ir_c[:, None])[:, 0] - r_lo
    dtheta = TWO_PI / n_t
    it = sector_index(yo, xo, n_t)
    cos_in = torch.clamp(vz, 0.0, 1.0)
    mu = v.ux * vx + v.uy * vy + v.uz * vz
    q_p = phase_function(geo.phase).pdf(mu, g) * cos_in / (t * t)
    q_u = torch.where(inside, 1.0 / torch.clamp(r * dr * dtheta, min=1e-30), torch.zeros_like(r))
    # G = w albedo exp(-t) T q_p / (q_p + q_u); S the same with T cos_in / cos_o for T and
    # q_p / cos_in = p / t^2 for q_p (see connect_uniform).
    base = torch.where(up & (q_p > 0), w * albedo * torch.exp(-t) / torch.clamp(q_p + q_u, min=1e-30), torch.zeros_like(w))
    G = base * fresnel_transmittance(cos_in, 1.0 / geo.eta) * q_p
    S = base * transmittance_cos_ratio(cos_in, 1.0 / geo.eta) * (phase_function(geo.phase).evaluate(mu, g) / (t * t))
    direction = _direction_bin(xo, yo, vx, vy, cos_in, geo)
    spatial = ir * n_t + it
    return G, S, spatial, direction


def _connect_both(v: Vertices, table: ConfigTable, geo: ConnectionGeometry):
    return connect_uniform(v, table, geo), connect_phase(v, table, geo)


@lru_cache(maxsize=None)
def connection_function(compiled: bool):
    """Both techniques for a chunk of vertices, compiled (static chunk size) or eager."""
    return compile_kernel(_connect_both, "connections") if compiled else _connect_both
