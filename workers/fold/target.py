"""Has a run reached its target error?  A pure decision on merged statistics.

A spec's ``target`` (:mod:`schema.target`) asks for relative standard errors on the total
diffuse reflectance Rd of every configuration and, optionally, on Rd(r) in the radial bins of a
radius range.  A run with a target folds its shards in shard order and, after each shard K,
calls :func:`target_status` on the merge of shards 0..K-1; the first K for which it says
``reached`` ends the run, and that merge is the result.  Because the decision depends only on
the merge of the first K shards (a deterministic function of spec and seed), K and the result
are reproducible bit for bit whatever the number of workers or the order shards finish in.

API (for every caller, `bssrdf simulate` and the job service alike)::

    status = target_status(result, spec.target)   # result: workers.fold.merge.Result of shards 0..K-1
    status.reached        # bool: every check met
    status.photons        # photons per configuration in the merged statistics
    status.worst          # the check furthest from its limit (largest rel_stderr / limit)
    status.checks         # every TargetCheck (quantity, estimator, configuration, figures)
    status.as_dict()      # JSON-ready summary (what the summary's "target" entry holds)

Checked, for each estimator row of the result, each configuration and the ``total`` component:
Rd against ``target.rel_stderr``; Rd(r) of every radial bin with r_lo >= r_min_mm and
r_hi <= r_max_mm against ``target.radial.rel_stderr``.  rel_stderr = stderr / |estimate|; an
estimate of 0 or a NaN standard error (no contributing event) never meets its limit.

A standard error counts only when it rests on at least MIN_UNITS = 30 independent units, i.e.
``dof = units - 1 >= MIN_DOF = 29`` (workers.fold.tally: photons for the exit tally and the hybrid,
batches for connections).  The estimated error of a mean from k units has k - 1 degrees of
freedom, and its own relative error is about 1 / sqrt(2 (k - 1)) (the spread of a chi-square
with k - 1 dof; Student's t): 41 % on the first shard of a run with 4 batches per shard (3 dof),
27 % with 8, 13 % at 29 dof.  A check with fewer is not met whatever its value (ratio inf: it
cannot be judged yet), so a batch-based estimate stops a run no sooner than after 30 batches
(with the default 4 per shard: 8 shards).

Stopping on the run's own error estimate is a sequential rule: the estimate at the stopping
shard is slightly biased (whether a shard stops the run depends a little on the estimate's own
fluctuation), by at most a fraction of the standard error reached, i.e. a relative bias below
the target itself.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from schema.target import TargetSpec

from .merge import Result

__all__ = ["MIN_DOF", "TargetCheck", "TargetStatus", "target_status"]

TOTAL = 2  # component index of "total" in the merged statistics
MIN_DOF = 29
"""Fewest degrees of freedom (independent units - 1) of a standard error a check counts on:
its relative error ~ 1 / sqrt(2 * 29) = 13 % (see the module docstring)."""


@dataclass(frozen=True)
class TargetCheck:
    """One checked quantity: ``Rd`` (r_lo_mm, r_hi_mm None) or ``Rd_r`` of one radial bin."""

    quantity: str
    estimator: str
    incidence_deg: float
    channel: str
    r_lo_mm: float | None
    r_hi_mm: float | None
    estimate: float  # G summed over the quantity's bins, per unit incident power
    stderr: float
    rel_stderr: float  # stderr / |estimate|; inf for an estimate of 0, nan without events
    limit: float
    dof: int  # degrees of freedom of stderr (photons - 1 or batches - 1)

    @property
    def met(self) -> bool:
        """rel_stderr <= limit on at least MIN_DOF degrees of freedom (False for nan and inf)."""
        return bool(self.dof >= MIN_DOF and self.rel_stderr <= self.limit)

    @property
    def ratio(self) -> float:
        """rel_stderr / limit: how far from the limit (<= 1 is met; nan, and a standard error on
        fewer than MIN_DOF degrees of freedom, count as inf)."""
        return math.inf if math.isnan(self.rel_stderr) or self.dof < MIN_DOF else self.rel_stderr / self.limit


@dataclass(frozen=True)
class TargetStatus:
    """The verdict on one merged result (see the module docstring)."""

    reached: bool
    photons: int
    worst: TargetCheck
    checks: tuple[TargetCheck, ...]

    def as_dict(self) -> dict:
        """reached, photons (per configuration), checks and met counts, and the worst check."""
        return {
            "reached": self.reached,
            "photons": self.photons,
            "checks": len(self.checks),
            "met": sum(c.met for c in self.checks),
            "worst": {k: _json_number(v) for k, v in asdict(self.worst).items()},
        }


def _json_number(v):
    """Floats that JSON can carry: inf and nan become None."""
    return None if isinstance(v, float) and not math.isfinite(v) else v


def _relative(estimate: float, stderr: float) -> float:
    if math.isnan(stderr):
        return math.nan
    return math.inf if estimate == 0.0 else stderr / abs(estimate)


def target_status(result: Result, target: TargetSpec) -> TargetStatus:
    """Check `target` on `result` (the merge of a run's first K shards); see the module docstring."""
    checks: list[TargetCheck] = []
    cfgs, layout = result.configs, result.layout
    for est in result.estimators:
        rd, rd_se = result.mean(f"{est}/Rd"), result.stderr(f"{est}/Rd")
        radial, radial_se = result.mean(f"{est}/radial_G"), result.stderr(f"{est}/radial_G")
        dof = result.dof(f"{est}/Rd")  # one unit count per estimator: Rd and its rings share it
        for cfg in range(cfgs.n):
            ch = cfgs.channel_of(cfg)
            where = dict(estimator=est, incidence_deg=float(cfgs.incidence_of(cfg)), channel=cfgs.channel_names[ch])
            m, se = float(rd[cfg, TOTAL]), float(rd_se[cfg, TOTAL])
            checks.append(TargetCheck("Rd", **where, r_lo_mm=None, r_hi_mm=None, estimate=m, stderr=se,
                                      rel_stderr=_relative(m, se), limit=target.rel_stderr, dof=dof))  # fmt: skip
            if target.radial is None:
                continue
            edges = layout.radial_mm[ch]
            inside = np.flatnonzero((edges[:-1] >= target.radial.r_min_mm) & (edges[1:] <= target.radial.r_max_mm))
            for i in inside:
                m, se = float(radial[cfg, TOTAL, i]), float(radial_se[cfg, TOTAL, i])
                checks.append(TargetCheck("Rd_r", **where, r_lo_mm=float(edges[i]), r_hi_mm=float(edges[i + 1]), estimate=m,
                                          stderr=se, rel_stderr=_relative(m, se), limit=target.radial.rel_stderr, dof=dof))  # fmt: skip
    worst = max(checks, key=lambda c: c.ratio)
    return TargetStatus(reached=all(c.met for c in checks), photons=int(result.n_sum), worst=worst, checks=tuple(checks))
