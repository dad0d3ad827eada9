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

- radial: r = sqrt(x^2 + y^2) / sigma_t in mm, against the configuration's row of edges by a
  branchless binary search (:func:`count_le`);
- cos_o: uniform bins, :func:`workers.walk.binning.uniform_index`; theta_s, phi_o: azimuth bins
  centred on 0, :func:`workers.walk.binning.azimuth_index`.

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

Every finished photon (exited, absorbed or truncated) is then recorded and its lane refilled by
:func:`finish_and_refill`, one pass over the lanes: per lane a (batch, configuration) key and the
absorbed and truncated weights, whose float sums the caller forms with an ordered bincount."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import torch

from .binning import azimuth_index, histogram_index, outgoing_azimuth, uniform_index
from .kernels import compile_kernel
from .optics import refracted_cos
from .walk import EMPTY, RUNNING, TRUNCATED, ConfigTable, Lanes, refill_lanes

__all__ = ["ExitBins", "batch_index", "count_le", "exit_bins", "exit_function", "finish_and_refill", "finish_function"]


@dataclass(frozen=True)
class ExitBins:
    """What the exit lookup needs, per shard.

    radial_mm: float64 [n_cfg, n_r + 1] radial edges of each configuration's channel (mm);
    sigma_t: float64 [n_cfg] (1/mm, optical -> mm); batch_starts: int64 [n_batches], the first
    photon index of each batch of the shard; n_theta, n_cos, n_phi: bin counts; inv_eta: 1/eta.
    """

    radial_mm: torch.Tensor
    sigma_t: torch.Tensor
    batch_starts: torch.Tensor
    n_theta: int
    n_cos: int
    n_phi: int
    inv_eta: float

    @property
    def n_r(self) -> int:
        return self.radial_mm.shape[1] - 1


def count_le(table: torch.Tensor, row: torch.Tensor, value: torch.Tensor) -> torch.Tensor:
    """Number of entries of table[row] that are <= value (int64), each table row sorted ascending.

    ``torch.searchsorted(table[row], value, right=True)`` elementwise, computed by binary lifting:
    k grows by the powers of two from the largest <= m down to 1 while the entry it would cover,
    table[row, k + step - 1], is still <= value.  A fixed number of gathers and no data-dependent
    loop, so it compiles into the surrounding elementwise kernel.  A NaN value counts 0.
    """
    m = table.shape[1]
    flat = table.reshape(-1)
    base = row * m
    k = torch.zeros_like(row)
    step = 1 << (m.bit_length() - 1)
    while step:
        cand = k + step
        entry = flat[base + torch.clamp(cand, max=m) - 1]
        k = torch.where((cand <= m) & (entry <= value), cand, k)
        step >>= 1
    return k


def batch_index(photon: torch.Tensor, batch_starts: torch.Tensor) -> torch.Tensor:
    """Batch of each photon index: the number of batch starts at or below it, minus one.

    The photon is never below the first start.  A few batches (the usual case) are counted by
    comparisons, which vectorize; many by :func:`count_le`'s search.
    """
    if batch_starts.shape[0] <= 16:
        return (photon[:, None] >= batch_starts[None, 1:]).sum(dim=1)
    return count_le(batch_starts[None, :], torch.zeros_like(photon), photon) - 1


def exit_bins(idx: torch.Tensor, lanes: Lanes, bins: ExitBins):
    """(flat, batch, G, S) of the exit events in lanes idx (int64 [E]); see the module docstring.

    flat: int64 histogram index [cfg, component, radial, theta_s, cos_o, phi_o]; batch: int64
    batch of the photon; G = w and S = w / cos_o float64.
    """
    cfg = lanes.cfg[idx]
    xd, yd = lanes.x[idx].double(), lanes.y[idx].double()
    r_mm = torch.sqrt(xd * xd + yd * yd) / bins.sigma_t[cfg]
    ir = torch.clamp(count_le(bins.radial_mm, cfg, r_mm) - 1, 0, bins.n_r)
    if bins.n_theta > 1:
        it = azimuth_index(torch.atan2(yd, xd), bins.n_theta)
    else:  # one theta_s bin (normal incidence): no angle needed
        it = torch.zeros_like(ir)
    # An exit refracted out, so cos_o > 0; the clamp only keeps a padding lane finite.
    cos_o = torch.clamp(refracted_cos(lanes.uz[idx].double(), bins.inv_eta), min=1e-300)
    ic = uniform_index(cos_o, 0.0, 1.0, bins.n_cos)
    ip = azimuth_index(outgoing_azimuth(xd, yd, lanes.ux[idx].double(), lanes.uy[idx].double()), bins.n_phi)
    comp = (lanes.nscat[idx] >= 2).to(torch.int64)
    n_sp = (bins.n_r + 1) * bins.n_theta
    n_dir = bins.n_cos * bins.n_phi
    flat = histogram_index(cfg, comp, ir * bins.n_theta + it, ic * bins.n_phi + ip, n_sp, n_dir)
    batch = batch_index(lanes.photon[idx], bins.batch_starts)
    wd = lanes.w[idx].double()
    return flat, batch, wd, wd / cos_o


@lru_cache(maxsize=None)
def exit_function(compiled: bool):
    """:func:`exit_bins` over a block of lane indices, compiled for one block size (the caller
    pads) or eager."""
    return compile_kernel(exit_bins, "exit_bins") if compiled else exit_bins


def finish_and_refill(lanes: Lanes, table: ConfigTable, launch: torch.Tensor, batch_starts: torch.Tensor):
    """Record the finished lanes and start new photons in every lane not running.

    For each lane, before the refill: key = batch * n_cfg + cfg of a finished photon (EXITED,
    ABSORBED or TRUNCATED), n_batches * n_cfg (a spare slot) for any other lane; its absorbed
    weight and truncated weight (float64, 0 for lanes not finished).  Then the refill of
    :func:`workers.walk.walk.refill_lanes` with `launch`.  Returns (key, absorbed, truncated, n_free,
    steps): n_free the lanes that were not running (the refill launched min(n_free, launches
    left) photons), steps the interaction steps of the finished photons (int64 scalars).  Only
    integer reductions: the float sums are left to the caller's ordered bincount, so results do
    not depend on how the kernel is threaded.
    """
    n_cfg, status = launch[3], lanes.status
    done = (status != RUNNING) & (status != EMPTY)
    batch = batch_index(lanes.photon, batch_starts)
    key = torch.where(done, batch * n_cfg + lanes.cfg, batch_starts.shape[0] * n_cfg)
    absorbed_d = torch.where(done, lanes.absorbed.double(), 0.0)
    truncated = torch.where(status == TRUNCATED, lanes.w.double(), 0.0)
    n_free = (status != RUNNING).sum()
    steps = torch.where(done, lanes.step.to(torch.int64), 0).sum()
    refill_lanes(lanes, table, launch)
    return key, absorbed_d, truncated, n_free, steps


@lru_cache(maxsize=None)
def finish_function(compiled: bool):
    """:func:`finish_and_refill`, compiled (static chunk shapes) or eager."""
    return compile_kernel(finish_and_refill, "finish_refill") if compiled else finish_and_refill
