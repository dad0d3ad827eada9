"""The hybrid estimator (the default): single scattering by connections from the first vertex,
multiple scattering by the exit tally.

Why: the connection estimator (:mod:`workers.walk.connections`) wins single scattering by one to two
orders of magnitude in efficiency (1 / (variance x CPU s)) and alone resolves it far from the
entry point, but connecting *every* vertex to *every* bin costs ~100 exit-walk steps per vertex
and loses multiple scattering by 17-65x (BENCHMARKS.md).  Single scattering only ever comes from
the first vertex, so:

- ``single``: at the first vertex of every photon, x_1 = s_1 u_0 (s_1 the walk's own first free
  path, u_0 the refracted incident direction, weight w_0 = 1 - R_spec), the flux leaving through
  a surface element after this one scattering,
      f(x_o) = w_0 a p(u_0 . w21) exp(-d) T21(cos_in) cos_in / d^2,
  is estimated by multiple importance sampling (balance heuristic, one sample per technique) of
  * the *phase* technique: the walk's own first scattering direction, followed to the surface,
    density per area q_p = p cos_in / d^2 (as in workers.walk.connections);
  * K_SAMPLES *stratified uniform* techniques: the spatial bins inside r_max, in flat order
    r * n_theta + theta, are cut into K contiguous strata; stratum j picks one bin uniformly and a
    point uniform in (r, theta) of it (theta_s bin k is [(k - 1/2) h, (k + 1/2) h), centred on
    +x: workers.walk.conventions): density q_j = 1 / (n_j r dr dtheta) in its n_j bins.
  A point x in stratum j gets the weight q/(q_p + q_j) for the technique q that drew it (only
  stratum j's density is nonzero there), so every contribution is bounded by w_0 a, as in the
  full connection estimator, at O(K) cost per photon instead of O(bins) per vertex.
- ``multiple``: the exit tally of photons that scattered twice or more (their exit bins, G = w,
  S = w / cos_o); exits after one scattering are not tallied (the connections replace them).

Both parts are unbiased for their component; total = single + multiple.  No weight depends on
the run's results.  S of a connection sample uses T cos_in / cos_o
(:func:`workers.walk.optics.transmittance_cos_ratio`), bounded also where cos_o -> 0.

Random numbers: the first vertex is recomputed from the photon's walk stream (the four draws of its first step: free path
and scattering direction, so the phase sample *is* the walk's direction) and the uniform samples
use the connection purpose of draw 0, block PURPOSE_CONNECT + j for stratum j.  The samples are
computed when a photon finishes, from its photon index and configuration alone, together with its
exit, so its contributions are squared per photon (workers.fold.tally).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import torch

from .binning import TWO_PI, direction_index, exact_divmod, histogram_index, sector_index
from .conventions import PURPOSE_CONNECT
from .harvest import ExitBins, exit_cells, harvest_block, spread_bins, spread_mask
from .kernels import compile_kernel
from .optics import fresnel_transmittance, refracted_cos, sample_exponential, scatter_direction, transmittance_cos_ratio
from .phase import DEFAULT_PHASE, phase_function
from .rng import philox4x32, photon_words, stream_draws, uniform_halfopen, uniform_open
from .search import EdgeIndex, indexed_count_le
from .walk import EXITED, Lanes, walk_stream_start

__all__ = ["K_SAMPLES", "FirstVertexGeometry", "EntryLayout", "strata", "first_vertex_samples", "photon_entries", "ENTRY_OUTPUTS", "harvest_with_entries", "harvest_entries_function"]

K_SAMPLES = 2
"""Stratified uniform samples per photon (fewer if there are fewer spatial bins)."""


def strata(n_bins: int, k: int) -> list[tuple[int, int]]:
    """K contiguous strata [floor(j n / k), floor((j + 1) n / k)) of n bins (k <= n)."""
    return [(j * n_bins // k, (j + 1) * n_bins // k) for j in range(k)]


@dataclass(frozen=True)
class FirstVertexGeometry:
    """What the first-vertex connections need, per shard (float32, optical units, like the walk).

    edges: [n_cfg, n_r + 1] radial edges of each configuration's channel; u0x, u0z, w0, albedo,
    g, k0, k1: per configuration (incident direction inside, 1 - R_spec, HG, Philox key words);
    n_theta, n_cos, n_phi; eta; k: stratified samples; hg_branch as in WalkParams; edge_index:
    the bucket index of edges, built from them (workers.walk.search).
    """

    edges: torch.Tensor
    u0x: torch.Tensor
    u0z: torch.Tensor
    w0: torch.Tensor
    albedo: torch.Tensor
    g: torch.Tensor
    k0: torch.Tensor
    k1: torch.Tensor
    n_theta: int
    n_cos: int
    n_phi: int
    eta: float
    k: int
    hg_branch: str
    phase: str = DEFAULT_PHASE  # the phase function (workers.walk.phase)
    edge_index: EdgeIndex | None = field(init=False, default=None)

    def __post_init__(self) -> None:
        object.__setattr__(self, "edge_index", EdgeIndex.build(self.edges))

    @property
    def n_r(self) -> int:
        return self.edges.shape[1] - 1


def _stratum_size(flat_bin: torch.Tensor, n_bins: int, k: int) -> torch.Tensor:
    """n_j of the stratum holding each flat bin b in [0, n_bins): the last stratum whose start
    floor(j n / k) is <= b, found by comparing with the k - 1 inner starts (k is a few; integer
    division would run lane by lane in the compiled kernel: workers.walk.binning.exact_divmod)."""
    bounds = strata(n_bins, k)
    size = torch.full_like(flat_bin, bounds[0][1] - bounds[0][0])
    for lo, hi in bounds[1:]:
        size = torch.where(flat_bin >= lo, hi - lo, size)
    return size


def first_vertex_samples(photon: torch.Tensor, cfg: torch.Tensor, geo: FirstVertexGeometry):
    """(spatial, direction, G, S), each [P, k + 1]: k stratified uniform samples then the phase
    sample of the first vertex of photons `photon` (int64 [P]) of configurations `cfg`.
    Computed in float32, as the walk is (the lookups of a sample's bin and its density use the
    same float32 edges, so the MIS weights are consistent); G and S are returned as float64.

    spatial = r * n_theta + theta (r = n_r beyond r_max: phase sample only); G and S float64 (0
    where the phase direction points down or is totally reflected).
    """
    spatial, direction, G, S, _ = (torch.stack(c, dim=1) for c in zip(*_first_vertex_columns(photon, cfg, geo)))
    return spatial, direction, G.double(), S.double()


def _first_vertex_columns(photon: torch.Tensor, cfg: torch.Tensor, geo: FirstVertexGeometry):
    """:func:`first_vertex_samples` as k + 1 columns (spatial, direction, G, S, radial) of [P]
    tensors, G and S float32, radial the spatial bin's ring (spatial // n_theta, carried so
    that no one divides it out again): the compiled entries work on whole columns, which
    vectorize over the photons (an [P, E] layout with E ~ 4 made inductor emit scalar loops)."""
    f32 = torch.float32
    n_r, n_t = geo.n_r, geo.n_theta
    n_bins = n_r * n_t
    c_lo, c_hi = photon_words(photon)
    k0, k1 = geo.k0[cfg], geo.k1[cfg]
    zero = torch.zeros_like(c_lo)
    (b0, _, b2, b3), _ = stream_draws(walk_stream_start(c_lo, c_hi, k0, k1))  # the walk's first step's draws
    s1 = sample_exponential(uniform_open(b0))  # the walk's first free path
    ux, uz = geo.u0x[cfg], geo.u0z[cfg]
    uy = torch.zeros_like(ux)
    px, pz = s1 * ux, s1 * uz
    wa = geo.w0[cfg] * geo.albedo[cfg]
    g = geo.g[cfg]
    edges = geo.edges[cfg]  # [P, n_r + 1]
    dtheta = TWO_PI / n_t

    # Phase technique: the walk's own scattering direction at the vertex.
    phase = phase_function(geo.phase)
    cos_t = phase.sample_cos(uniform_halfopen(b2), geo.g[cfg], geo.hg_branch)
    vx, vy, vz = scatter_direction(ux, uy, uz, cos_t, uniform_halfopen(b3) * (2.0 * torch.pi))
    up = vz > 0
    t = -pz / torch.clamp(vz, min=1e-30)
    xo, yo = px + t * vx, t * vy  # the vertex lies in the incidence plane (y = 0)
    r = torch.sqrt(xo * xo + yo * yo)
    ir = torch.clamp(indexed_count_le(geo.edges, geo.edge_index, cfg, r) - 1, 0, n_r)
    it = sector_index(yo, xo, n_t)
    inside = ir < n_r
    irc = torch.clamp(ir, max=n_r - 1)
    dr = edges.gather(1, irc[:, None] + 1)[:, 0] - edges.gather(1, irc[:, None])[:, 0]
    sb = irc * n_t + it
    q_u = torch.where(inside, 1.0 / torch.clamp(_stratum_size(sb, n_bins, geo.k) * r * dr * dtheta, min=1e-30), 0.0)
    cos_in = torch.clamp(vz, 0.0, 1.0)
    p = phase.pdf(ux * vx + uz * vz, g)  # = evaluate: sampled exactly (workers.walk.phase)
    tt = torch.clamp(t * t, min=1e-30)
    q_p = p * cos_in / tt
    base = torch.where(up & (q_p > 0), wa * torch.exp(-t) / torch.clamp(q_p + q_u, min=1e-30), 0.0)
    G_p = base * fresnel_transmittance(cos_in, 1.0 / geo.eta) * q_p
    S_p = base * transmittance_cos_ratio(cos_in, 1.0 / geo.eta) * (p / tt)
    sp_p = ir * n_t + it
    dir_p = direction_index(refracted_cos(cos_in, 1.0 / geo.eta), xo, yo, vx, vy, geo.n_cos, geo.n_phi)

    # Stratified uniform techniques: one block of four uniforms per stratum.
    cols = []
    for j, (lo, hi) in enumerate(strata(n_bins, geo.k)):
        u = philox4x32(c_lo, c_hi, zero, zero + (PURPOSE_CONNECT + j), k0, k1)
        u_bin, u_r, u_t = (uniform_halfopen(x) for x in u[:3])
        n_j = hi - lo
        b = lo + torch.clamp((u_bin * n_j).to(torch.int64), max=n_j - 1)
        jr, jt = exact_divmod(b, n_t)
        r_lo = edges.gather(1, jr[:, None])[:, 0]
        drj = edges.gather(1, jr[:, None] + 1)[:, 0] - r_lo
        rr = r_lo + u_r * drj
        th = (jt.to(f32) - 0.5 + u_t) * dtheta  # uniform in the centred bin [(jt - 1/2) h, (jt + 1/2) h)
        xs, ys = rr * torch.cos(th), rr * torch.sin(th)
        dx, dy, dz = xs - px, ys, -pz
        d2 = dx * dx + dy * dy + dz * dz
        d = torch.sqrt(d2)
        cin = dz / d
        pj = phase.pdf((ux * dx + uz * dz) / d, g)
        qpj = pj * cin / d2
        # q_j is infinite at r = 0: the clamp makes this sample's weight exactly 0 there.
        qj = 1.0 / torch.clamp(n_j * rr * drj * dtheta, min=1e-30)
        bj = wa * torch.exp(-d) / (qpj + qj)
        dir_j = direction_index(refracted_cos(cin, 1.0 / geo.eta), xs, ys, dx, dy, geo.n_cos, geo.n_phi)
        cols.append((b, dir_j, bj * fresnel_transmittance(cin, 1.0 / geo.eta) * qpj, bj * transmittance_cos_ratio(cin, 1.0 / geo.eta) * (pj / d2), jr))
    cols.append((sp_p, dir_p, G_p, S_p, ir))
    return cols


@dataclass(frozen=True)
class EntryLayout:
    """Histogram geometry of the hybrid's entries (workers.fold.tally): n_sp = (n_r + 1) n_theta
    spatial and n_dir = n_cos n_phi direction bins; square_offsets: where the squared sums of
    bins_G, bins_S, radial_G and Rd start in one histogram (workers.fold.tally._Layout)."""

    n_sp: int
    n_dir: int
    n_theta: int
    square_offsets: tuple[int, int, int, int]


def photon_entries(idx: torch.Tensor, lanes: Lanes, bins: ExitBins, geo: FirstVertexGeometry, lay: EntryLayout):
    """Every entry of the photons finished in lanes idx, and their squares per photon.

    Per photon E = k + 2 entries: the k uniform and the phase first-vertex samples (single) and
    the exit if it scattered two or more times (multiple; G = S = 0 otherwise).  Returns
    (flat2, G, S) [P, E] with flat2 the index [cfg, comp (0/1), spatial, direction], and
    (square_key, square_weight) [Q, P]: keys into the squares histogram (bins_G, bins_S,
    radial_G and Rd, each with the components single, multiple and total: the square_offsets
    regions) and values which, summed per key and completed by :func:`workers.fold.tally.fold_square_totals`,
    are the sum over photons of the photon's squared contribution at every key.

    A photon's squares split by component: its single entries share keys only among themselves
    (x_j (x_j + 2 sum of the later single x_l with the key of x_j), as in
    :func:`workers.fold.tally.photon_moments`), its exit is alone in the multiple component
    (x_e^2), and at the total level (sum_j x_j + x_e)^2 = the single part + x_e^2 + 2 x_e sum
    of the single x_j in the exit's bin.  So the total level needs one cross term per level
    (at the exit's total key), the components' squares being added to it once per block:
    Q = 3 (E + 1) + 3 values per photon, where squaring every entry at every level and component
    took 8 E (18 against 32 at E = 4; bincounting them was the hybrid's largest Python cost).
    Rd's single part is one value, (sum of the single G)^2; Rd's three rows come last.  Where
    the phase sample's values are 0, their keys are spread over the bins (below).

    The results are contiguous along the photons (flat2, G and S are views of [E, P] storage):
    computed as columns over the photons, the kernel is one vectorized loop (built as [P, E],
    inductor emitted scalar loops for the short entry axis and ran 25 % slower).
    """
    cfg = lanes.cfg[idx]
    cols = _first_vertex_columns(lanes.photon[idx], cfg, geo)
    _, _, ir_e, spatial_e, direction_e, ge, se = exit_cells(idx, lanes, bins)
    keep = (lanes.status[idx] == EXITED) & (lanes.nscat[idx] >= 2)
    # Columns e = 0 .. E - 1 of [P] tensors: the first-vertex samples (component 0), then the exit (1).
    spatial = [c[0] for c in cols] + [spatial_e]
    direction = [c[1] for c in cols] + [direction_e]
    radial = [c[4] for c in cols] + [ir_e]
    g = [c[2].double() for c in cols] + [torch.where(keep, ge, 0.0)]
    s = [c[3].double() for c in cols] + [torch.where(keep, se, 0.0)]
    e = len(spatial)
    ns = e - 1  # the single entries; entry ns is the exit
    comp = [0] * ns + [1]
    flat2 = [histogram_index(cfg, comp[j], spatial[j], direction[j], lay.n_sp, lay.n_dir) for j in range(e)]
    o_bins_g, o_bins_s, o_radial, o_rd = lay.square_offsets
    n_r1 = lay.n_sp // lay.n_theta
    bins3 = lambda c, j: histogram_index(cfg, c, spatial[j], direction[j], lay.n_sp, lay.n_dir, n_comp=3)  # noqa: E731
    levels = (  # (key of component c for entry j, values)
        (lambda c, j: bins3(c, j) + o_bins_g, g),
        (lambda c, j: bins3(c, j) + o_bins_s, s),
        (lambda c, j: (cfg * 3 + c) * n_r1 + radial[j] + o_radial, g),
    )
    zero = torch.zeros_like(g[0])
    keys, weights, phase_rows = [], [], []
    for key_of, value in levels:
        single = [key_of(0, j) for j in range(ns)]
        for j in range(ns):
            cross = sum((torch.where(single[i] == single[j], value[i], 0.0) for i in range(j + 1, ns)), zero)
            phase_rows += [len(keys)] if j == ns - 1 else []
            keys.append(single[j])
            weights.append(value[j] * (value[j] + 2.0 * cross))
        x_e = value[ns]
        keys.append(key_of(1, ns))
        weights.append(x_e * x_e)
        at_exit = key_of(0, ns)  # the exit's bin in the single component: equal keys = one total bin
        shared = sum((torch.where(single[j] == at_exit, value[j], 0.0) for j in range(ns)), zero)
        keys.append(key_of(2, ns))
        weights.append(2.0 * x_e * shared)
    # The phase sample's values of 0 go to spread keys (workers.walk.harvest.spread_mask): it
    # points down for half the photons, and its zeros in one bin made one chain of dependent
    # additions in each bincount.  (Spreading every entry's zeros cost the kernel more than it
    # saved.)
    pos = torch.arange(idx.shape[0], dtype=torch.int64)
    spread_sq = o_bins_g + (pos & spread_mask(o_bins_s - o_bins_g))
    phase = ns - 1
    flat2[phase] = torch.where((g[phase] == 0.0) & (s[phase] == 0.0), pos & spread_mask(spread_bins(bins)), flat2[phase])
    for at in phase_rows:
        keys[at] = torch.where(weights[at] == 0.0, spread_sq, keys[at])
    g_single, g_e = sum(g[:ns], zero), g[ns]
    keys += [cfg * 3 + c + o_rd for c in range(3)]
    weights += [g_single * g_single, g_e * g_e, 2.0 * g_e * g_single]
    # Entry-major storage ([E, P], contiguous along the photons, so every loop vectorizes).
    return (torch.stack(flat2).T, torch.stack(g).T, torch.stack(s).T, torch.stack(keys), torch.stack(weights))


ENTRY_OUTPUTS = 5
"""The arrays :func:`photon_entries` returns, first among :func:`harvest_with_entries`'s outputs."""


def harvest_with_entries(idx, n_valid, lanes: Lanes, table, launch, bins: ExitBins, geo: FirstVertexGeometry, lay: EntryLayout,
                         members: bool = False):
    """The hybrid's harvest in one pass over lanes idx: :func:`photon_entries` of their photons,
    read before the refill, then :func:`workers.walk.harvest.harvest_block` without the exit
    tally's lookup (the entries carry the exit).  Returns the entries' ENTRY_OUTPUTS arrays, then
    the records of ``harvest_fields(False, members)``.

    One pass gathers the lanes' fields once where the entries and the harvest each gathered
    them, and makes one call instead of two.  Its caller tallies the entries only where every
    lane of idx holds a finished photon, which outside the shard's first fill is every harvest
    (workers.run.shard), which also gives the padding lanes' entries weight 0."""
    entries = photon_entries(idx, lanes, bins, geo, lay)
    return (*entries, *harvest_block(idx, n_valid, lanes, table, launch, bins, exits=False, members=members))


@lru_cache(maxsize=None)
def harvest_entries_function(compiled: bool, members: bool = True):
    """:func:`harvest_with_entries` compiled for any block length (a multiple of the vector width:
    the caller pads) or eager."""

    def fn(idx, n_valid, lanes, table, launch, bins, geo, lay):
        return harvest_with_entries(idx, n_valid, lanes, table, launch, bins, geo, lay, members)

    return compile_kernel(fn, "harvest_entries", (members,), any_length=True) if compiled else fn
