"""Path-length roulette (the spec's ``path_roulette``, :mod:`schema.roulette`).

**What.**  A photon still RUNNING when its step count (``Lanes.step``, the random draw index: one
per free path, scatterings and surface reflections alike) reaches start, 2 start, 4 start, ...
plays Russian roulette: with the uniform u of Philox counter (photon, step, PURPOSE_ROULETTE)
under the configuration's key, it survives if u < s and its weight is divided by s; otherwise it
ends with weight 0 (status ABSORBED, as the walk's weight roulette ends a photon).

**Unbiased.**  Given the path so far, a round multiplies the weight by R with E[R] = s (1 / s) +
(1 - s) 0 = 1, and R is independent of everything the path does afterwards (its own counter
purpose), so every tally's expectation -- exits, first-vertex connections (made before any
round: start >= 16 steps), truncated weight, and the deposit-per-collision absorbed power (in
expectation) -- is the one without it.  The rounds depend on the step count alone, not on the
weight or the albedo, so a shared walk (:mod:`workers.reweight`) stays exact: a member's weight
w (a / a_w)^n carries the same factors R, whose mean is 1 whatever a.

**Why it pays.**  At albedo ~1 a half-space walk's path lengths have a heavy tail (the chance of
a path lasting n steps falls only like n^-1/2), so an albedo-1 walk spends most of its steps on
few long paths up to the cap ``max_scatter``.  Those paths exit far from the entry point (their
spread grows like sqrt(n) mean free paths), beyond a table's radii, and the members of a shared
walk at a < 1 weight them by a^n ~ 0: roulette ends most of them at little cost in variance.  The
variance it adds is that of the weights 1 / s^k of the paths that survive k rounds: at albedo 1
a path reaches the k-th round with probability ~ (1/sqrt 2)^k (without rounds) times s^k, so
the added second moment grows like (1 / (sqrt 2 s))^k, bounded as the cap grows iff
s >= 1/sqrt 2; below it the estimates stay unbiased but become skewed (a few rare heavy paths
carry the missing mean), and error bars from few photons understate.  At smaller albedos
absorption ends the long paths anyway.  Whether a setting pays is measured per node
(``python -m workers.measure.table_cost --path-roulette``, BENCHMARKS.md).

**Determinism.**  A round happens at an exact step count of the photon: every lane is stepped
EXIT_STEPS_PER_CALL (a power of two <= start) steps per call from its launch, and the compiled
step plays the round of the call's due lanes after its last step (:func:`round_outcome`, traced
into :func:`workers.walk.walk.step_function`; the vertices of that step are taken first, so they
precede the round).  The outcome depends on the photon's index, its configuration's key and its
step count, never on its lane, the lane count or the threads.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from .conventions import PURPOSE_ROULETTE
from .rng import philox4x32, uniform_halfopen

if TYPE_CHECKING:
    from .walk import Lanes

__all__ = ["check_steps_per_call", "round_outcome", "roulette_round"]


def check_steps_per_call(start: int, n_steps: int) -> None:
    """The runner applies rounds between calls of n_steps steps: start must be a multiple."""
    if start % n_steps:
        raise ValueError(f"path_roulette.start {start} must be a multiple of the walk's steps per call {n_steps}")


def round_outcome(running: torch.Tensor, step: torch.Tensor, w: torch.Tensor, c_lo: torch.Tensor, c_hi: torch.Tensor,
                  k0: torch.Tensor, k1: torch.Tensor, start: int, survival: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(weight after the round, ended) per lane, elementwise: a running lane whose step count is
    start * 2^k (k >= 0, start a power of two) is due; it survives where its round's uniform
    (Philox counter (photon, step, PURPOSE_ROULETTE)) is below survival, its weight divided by
    survival, and ends (weight 0; the caller marks it ABSORBED) where not.  No indexing, so it
    fuses into the compiled step."""
    due = running & (step >= start) & ((step & (step - 1)) == 0)
    u = uniform_halfopen(philox4x32(c_lo, c_hi, step, torch.full_like(step, PURPOSE_ROULETTE), k0, k1)[0])
    live = u < survival
    return torch.where(due, torch.where(live, w * (1.0 / survival), 0.0), w), due & ~live


def roulette_round(lanes: Lanes, start: int, survival: float) -> int:
    """Play the round of every RUNNING lane whose step count is start * 2^k (k >= 0), in place
    (eagerly: the walk plays it inside its compiled step); returns the number of photons it ended."""
    from .walk import ABSORBED, RUNNING  # the walk imports this module

    w, ended = round_outcome(lanes.status == RUNNING, lanes.step, lanes.w, lanes.c_lo, lanes.c_hi, lanes.k0, lanes.k1, start, survival)
    lanes.w.copy_(w)
    lanes.status.copy_(torch.where(ended, ABSORBED, lanes.status))
    return int(ended.sum())
