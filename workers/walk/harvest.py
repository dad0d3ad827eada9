"""The harvest of finished lanes, in compiled passes: the exit tally's bin lookup, and the walk
totals recorded in the same pass as the refill.

When the shard runner harvests the lanes whose photons exited, each exit event needs its flat
histogram index [cfg, component, radial (n_r = beyond r_max), theta_s, cos_o, phi_o], its batch
(the number of batch starts at or below its photon index, as ``np.searchsorted(starts, photon,
"right") - 1``) and its contributions to G (the weight w) and to S (w / cos_o), cos_o being the
cosine of the refracted direction outside.  :func:`exit_bins` computes them elementwise (no search,
no sort) so that torch.compile fuses the whole lookup into one loop over the events: done as eager
tensor operations it was a pass over the events per operation and cost, on short paths (M2), as
much as the walk itself.  The lookups are exact with respect to the stored edges, in float64, as
the tables' edges are:

- radial: r = sqrt(x^2 + y^2) / sigma_t in mm, against the configuration's row of edges through
  their bucket index (:func:`workers.walk.search.indexed_count_le`: a gather and a comparison
  where a binary search took six dependent gathers);
- cos_o: uniform bins, :func:`workers.walk.binning.uniform_index`; theta_s, phi_o: azimuth bins
  centred on 0, :func:`workers.walk.binning.sector_index` (by cross products with the edge directions).

S of an exit, w / cos_o, is unbiased for the bin's BSSRDF averaged over dA d(omega) (the flux
through a bin is the integral of L cos_o, so the integral of L is the sum of w / cos_o), and has
a finite variance except in one case: at eta = 1 the exits' density in cos_o is ~ cos_o near
grazing (the radiance is finite there), so in the lowest cos bin E[(w / cos_o)^2] ~ int dc / c
diverges logarithmically (for eta > 1 the transmittance vanishes like cos_o and the density goes
like cos_o^2: finite).  It is kept: the estimate is unbiased and, its truncated second moment
being slowly varying (~ ln N), in the normal domain of attraction, where the per-photon standard
error is asymptotically exact (Gine, Goetze and Mason 1997: the self-normalised sum converges to
N(0, 1)); convergence is sqrt(ln N / N) rather than 1 / sqrt(N).  A bounded alternative such as
G / (A * projected solid angle) estimates another quantity (S averaged with weight cos_o) and is
biased for this one wherever the radiance varies over the bin.  tests/workers/test_walk_exact.py
checks S per (r, cos_o) bin, the grazing bin at eta = 1 included, against the quadrature.

At finite N that error bar is honest for the difference of two runs but not for one run against
the truth, so the tables flag these bins (bins.parquet ``S_infinite_variance`` = 1, ``S_stderr``
NaN: workers.fold.output.s_infinite_variance).  Measured (eta = 1, g = 0.9, albedo 0.9, roulette, 6e4 photons, ~280 grazing exits per
(r, phi_o) bin, 20 seeds): two-seed z of the grazing S have unit spread (tests/workers/
test_walk_errors.py passes), while t of one run against the mean of the other 19 has mean -0.20,
variance 1.26 and skew -0.56 (G of the same bins: -0.04, 0.85, +0.17): a run that misses the rare
near-grazing exits is low and reports a small error.  A model of the bin (density 2 c / c1^2)
gives the same, P(t < -3) = 1 % against 0.13 %, fading like 1 / ln N.  No function of the exit
alone does better: w / cos_o is the only unbiased weight for every radiance.  A finite-variance
estimate needs the vertex: a next-flight estimate of the grazing bin from every vertex at depth
z, w p(omega) exp(-sigma_t z / c) / c over the density the direction omega was drawn with, has a
finite second moment when c is drawn in the bin by a density ~ c^(-1/2) or steeper (drawn from
the phase function it still diverges logarithmically); in a one-vertex model E[x^2] stays flat
from 1e4 to 1e7 samples and t has mean -0.04, variance 1.02 (exit tally: -0.20, 1.16).

Every lane not running is then recorded and refilled by :func:`harvest_block`, one compiled
pass over a block of those lanes' indices that also makes the exit tally's entries: per lane
a (batch, configuration) key, the absorbed and truncated weights and the exit's (flat, G, S),
whose float sums the caller forms with ordered bincounts.  The work is per harvested lane: an
earlier version refilled with one pass over every lane of the array and looked exits up in a
second kernel, and on short paths (M2) that cost more than the walk (BENCHMARKS.md)."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import torch

from .binning import direction_index, exact_divmod, histogram_index, sector_index
from .kernels import compile_kernel
from .optics import refracted_cos
from .search import EdgeIndex, count_le, indexed_count_le
from .walk import EMPTY, EXITED, RUNNING, TRUNCATED, ConfigTable, Lanes, refill_at

__all__ = ["ExitBins", "batch_index", "exit_bins", "exit_cells", "harvest_block", "harvest_fields", "harvest_function", "spread_bins", "spread_mask"]


@dataclass(frozen=True)
class ExitBins:
    """What the exit lookup needs, per shard.

    radial_mm: float64 [n_cfg, n_r + 1] radial edges of each configuration's channel (mm);
    sigma_t: float64 [n_cfg] (1/mm, optical -> mm); batch_starts: int64 [n_batches], the first
    photon index of each batch of the shard; n_theta, n_cos, n_phi: bin counts; inv_eta: 1/eta;
    radial_index: the bucket index of radial_mm, built from it (workers.walk.search).
    """

    radial_mm: torch.Tensor
    sigma_t: torch.Tensor
    batch_starts: torch.Tensor
    n_theta: int
    n_cos: int
    n_phi: int
    inv_eta: float
    radial_index: EdgeIndex | None = field(init=False, default=None)

    def __post_init__(self) -> None:
        object.__setattr__(self, "radial_index", EdgeIndex.build(self.radial_mm))

    @property
    def n_r(self) -> int:
        return self.radial_mm.shape[1] - 1


def batch_index(photon: torch.Tensor, batch_starts: torch.Tensor) -> torch.Tensor:
    """Batch of each photon index: the number of batch starts at or below it, minus one.

    The photon is never below the first start.  A few batches (the usual case) are counted by
    comparisons, which vectorize; many by :func:`workers.walk.search.count_le`'s binary search.
    """
    if batch_starts.shape[0] <= 16:
        return (photon[:, None] >= batch_starts[None, 1:]).sum(dim=1)
    return count_le(batch_starts[None, :], torch.zeros_like(photon), photon) - 1


def exit_bins(idx: torch.Tensor, lanes: Lanes, bins: ExitBins):
    """(flat, batch, G, S) of the exit events in lanes idx (int64 [E]); see the module docstring.

    flat: int64 histogram index [cfg, component, radial, theta_s, cos_o, phi_o]; batch: int64
    batch of the photon; G = w and S = w / cos_o float64.
    """
    cfg, comp, _, spatial, direction, g, s = exit_cells(idx, lanes, bins)
    flat = histogram_index(cfg, comp, spatial, direction, (bins.n_r + 1) * bins.n_theta, bins.n_cos * bins.n_phi)
    return flat, batch_index(lanes.photon[idx], bins.batch_starts), g, s


def exit_cells(idx: torch.Tensor, lanes: Lanes, bins: ExitBins):
    """The parts of :func:`exit_bins`'s flat index, for a caller that keys other histograms by
    them (the hybrid): (cfg, component, radial ir, spatial ir * n_theta + it, direction, G, S).
    Taking a flat index apart again would divide int64 lane by lane (exact_divmod)."""
    cfg = lanes.cfg[idx]
    xd, yd = lanes.x[idx].double(), lanes.y[idx].double()
    r_mm = torch.sqrt(xd * xd + yd * yd) / bins.sigma_t[cfg]
    ir = torch.clamp(indexed_count_le(bins.radial_mm, bins.radial_index, cfg, r_mm) - 1, 0, bins.n_r)
    it = sector_index(yd, xd, bins.n_theta)
    # An exit refracted out, so cos_o > 0; the clamp only keeps a padding lane finite.
    cos_o = torch.clamp(refracted_cos(lanes.uz[idx].double(), bins.inv_eta), min=1e-300)
    direction = direction_index(cos_o, xd, yd, lanes.ux[idx].double(), lanes.uy[idx].double(), bins.n_cos, bins.n_phi)
    comp = (lanes.nscat[idx] >= 2).to(torch.int64)
    wd = lanes.w[idx].double()
    return cfg, comp, ir, ir * bins.n_theta + it, direction, wd, wd / cos_o


def spread_mask(n_bins: int) -> int:
    """Where entries of weight 0 go: flat j & spread_mask(n), the largest power of two <= n
    bins, minus one (j is the position in the block).  The tallies
    take every record without selecting (selecting costs more than adding the zeros), and +0.0
    leaves any sum of non-negative values as it is, in whatever bin; but zeros all in one bin
    make the bincount one chain of dependent additions through memory (a third of M2's photons
    end without an exit: about 2 against 1.2 ns a record), spread they run in parallel."""
    return (1 << (int(n_bins).bit_length() - 1)) - 1


def spread_bins(bins: ExitBins) -> int:
    """The bins of configuration 0, over which the exit tally's zeros are spread (spread_mask)."""
    return 2 * (bins.n_r + 1) * bins.n_theta * bins.n_cos * bins.n_phi


def harvest_fields(exits: bool = True, members: bool = True) -> tuple[str, ...]:
    """Names of the records :func:`harvest_block` returns, in order: the exit entries only with
    the exit tally, the lane's status, scattering count and weight only for reweighted members.
    A kernel writes every array it returns, read or not (the step's unused vertex arrays once
    cost a fifth of an M2 step call)."""
    return (*(("flat", "g", "s") if exits else ()), "key", "absorbed", "truncated", "steps",
            *(("status", "nscat", "w") if members else ()))  # fmt: skip


def harvest_block(idx: torch.Tensor, n_valid: torch.Tensor, lanes: Lanes, table: ConfigTable, launch: torch.Tensor, bins: ExitBins,
                  exits: bool = True, members: bool = True):
    """Record the photons of lanes idx and refill those lanes: the harvest's work per lane that
    is not running, not per lane of the array.

    idx: int64 [B] lanes in ascending order, its first n_valid (an int64 scalar) real, the rest
    padding that points at a scratch lane beyond the stepped ones; launch = int64 [start photon,
    launch number of position 0, launches in the shard, configurations].  Position j records,
    before the refill:
    - flat, G, S (only with ``exits``): the exit tally's entry (:func:`exit_bins`) if the lane
      EXITED, else G = S = 0 at flat j & spread_mask(spread_bins), which leave every sum of the tally
      as it is (a run without the exit tally -- the hybrid makes its own entries -- skips the
      lookup);
    - key = batch * n_cfg + cfg of a finished photon (EXITED, ABSORBED or TRUNCATED), else
      n_batches * n_cfg (a spare slot); its absorbed weight and its truncated weight (float64, 0
      for lanes not finished); steps: the interaction steps of the block's finished photons
      (an int64 scalar: an integer sum, the same in any order);
    - status, nscat and w (with ``members``): the lane's state, for reweighted members
      (workers.fold.reweight).
    The records are returned in the order of :func:`harvest_fields`.
    Then position j (valid) gets launch number q = launch[1] + j, photon start + q // n_cfg of
    configuration q % n_cfg, while q < launches; other valid lanes become EMPTY
    (:func:`workers.walk.walk.refill_at`): over a harvest's blocks, the k-th lane not running
    (in lane order) gets launch number next + k.  No float reductions: the caller sums with
    ordered bincounts, so results do not depend on how the kernel is threaded.
    """
    start, nxt, n_launch, n_cfg = launch[0], launch[1], launch[2], launch[3]
    pos = torch.arange(idx.shape[0], dtype=torch.int64)
    valid = pos < n_valid
    status = lanes.status[idx]
    done = valid & (status != RUNNING) & (status != EMPTY)
    exited = valid & (status == EXITED)
    if exits:
        flat, batch, g, s = exit_bins(idx, lanes, bins)
        flat = torch.where(exited, flat, pos & spread_mask(spread_bins(bins)))
        g, s = torch.where(exited, g, 0.0), torch.where(exited, s, 0.0)
    else:
        batch = batch_index(lanes.photon[idx], bins.batch_starts)
    key = torch.where(done, batch * n_cfg + lanes.cfg[idx], bins.batch_starts.shape[0] * n_cfg)
    absorbed = torch.where(done, lanes.absorbed[idx].double(), 0.0)
    w = lanes.w[idx]
    truncated = torch.where(valid & (status == TRUNCATED), w.double(), 0.0)
    steps = torch.where(done, lanes.step[idx], 0).sum(dtype=torch.int64)
    records = {"key": key, "absorbed": absorbed, "truncated": truncated, "steps": steps, "status": status, "nscat": lanes.nscat[idx], "w": w}
    if exits:
        records.update(flat=flat, g=g, s=s)
    out = tuple(records[name] for name in harvest_fields(exits, members))  # read before the refill writes the lanes
    q = nxt + pos
    new = valid & (q < n_launch)
    photon, cfg = exact_divmod(torch.where(new, q, 0), n_cfg)
    refill_at(lanes, table, idx, start + photon, cfg, new, valid)
    return out


@lru_cache(maxsize=None)
def harvest_function(compiled: bool, exits: bool = True, members: bool = True):
    """:func:`harvest_block` with or without the exit tally's lookup and the members' records
    (:func:`harvest_fields`), compiled for any block length (a multiple of the vector width: the
    caller pads) or eager."""

    def fn(idx, n_valid, lanes, table, launch, bins):
        return harvest_block(idx, n_valid, lanes, table, launch, bins, exits, members)

    return compile_kernel(fn, "harvest_block", (exits, members), any_length=True) if compiled else fn
