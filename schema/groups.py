"""Walk groups of a sweep: which albedos share one random walk (``"walks": "shared"``).

With weights and Russian roulette (implicit capture) the geometry of a photon's path does not
depend on the single-scattering albedo: only its weight does, by a factor a per scattering
event.  A photon walked at albedo a_w that leaves after n scatterings with weight w therefore
also estimates, without bias, what it would contribute at any albedo a <= a_w:

    w (a / a_w)^n

(workers/fold/reweight.py derives this, roulette and the path cap included).  A sweep with shared
walks walks each *group* of albedos of one (g, eta) once, at the group's largest albedo (its
*leader*), and tallies every member from that walk.  The groups are contiguous ranges of the
ascending albedo axis cut at ``group_edges``: a group starts at each edge (the first albedo
>= the edge), so with edges (e_1 < e_2 < ...) the groups are [0, e_1), [e_1, e_2), ..., [e_k, 1].
Empty ranges are dropped.

Why these edges (:data:`DEFAULT_GROUP_EDGES`): a member's variance per photon is about that of
its own direct walk (the reweighted weight is the direct walk's weight a^n w_0 with less roulette
noise; far nodes of low albedos are the exception when a_w is much larger), so a group costs (the photons its hardest member needs) x (CPU
per photon at the leader's albedo, plus the members' tallies).  Measured for pbrt's table at
g 0, eta 1.33 with the hybrid (BENCHMARKS.md, "Table cost"): every albedo >= 0.7 needs about the
same photons (~1.7e7, set by the innermost radius node), so they all ride on the walk at the
largest albedo for free; below 0.7 the far nodes (~9 mean free paths) need 1e8-1e9 photons,
which a walk at albedo ~1 makes expensive (a^n spreads the weights of long paths: one group for
all albedos projected 27x the cost of these three groups), and cheap walks at 0.3-0.7 serve.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Sequence

if TYPE_CHECKING:
    from .spec import SimulationSpec

__all__ = ["DEFAULT_GROUP_EDGES", "STRETCH_GROUP_EDGES", "SHARED_ESTIMATORS", "default_group_edges", "albedo_groups", "walk_mode", "walk_groups"]

DEFAULT_GROUP_EDGES: tuple[float, ...] = (0.3, 0.7)
"""Albedos where a new walk group starts when a sweep does not give ``group_edges``."""

STRETCH_GROUP_EDGES: tuple[float, ...] = (0.3, 0.4, 0.5, 0.6, 0.7)
"""The default edges of a sweep with ``stretch`` (schema.stretch): stretched walks reach the far
nodes, and what is left to decide their cost is the reweighting from the leader, whose factor
(a / a_w)^n thins the many-scattering paths that reach far out; leaders 0.1 apart below 0.7 keep
it mild.  Measured for pbrt's table at g 0, eta 1.33 (BENCHMARKS.md, "Far tails"): the ten albedos
in [0.33, 0.68] need 4.2e8 photons with these edges and no stretching, 4.0e8 with stretching and
one group, 4.7e7 with both."""

SHARED_ESTIMATORS = ("exits", "hybrid")
"""Estimators whose tallies a shared walk reweights (per photon: its exit and first vertex)."""


def albedo_groups(albedos: Sequence[float], edges: Sequence[float]) -> list[tuple[int, int]]:
    """Index ranges [lo, hi) of the ascending ``albedos`` cut where an albedo reaches an edge
    (each edge starts a group at the first albedo >= edge); empty ranges dropped."""
    cuts = sorted({sum(1 for a in albedos if a < e) for e in edges} | {0, len(albedos)})
    return [(lo, hi) for lo, hi in zip(cuts[:-1], cuts[1:]) if hi > lo]


def default_group_edges(spec: "SimulationSpec") -> tuple[float, ...]:
    """The group edges of a sweep that does not give ``group_edges``: STRETCH_GROUP_EDGES with
    ``stretch``, else DEFAULT_GROUP_EDGES."""
    return STRETCH_GROUP_EDGES if spec.stretch is not None else DEFAULT_GROUP_EDGES


def walk_mode(spec: "SimulationSpec") -> str:
    """"shared" or "independent": the sweep's ``walks``, or, when not given, shared if the
    estimator is one a shared walk can reweight (exits, hybrid) with weights absorption and
    the sweep has several albedos, else independent.  A single medium: independent."""
    sweep = spec.sweep
    if sweep is None:
        return "independent"
    if sweep.walks is not None:
        return sweep.walks
    ok = spec.estimator in SHARED_ESTIMATORS and spec.absorption == "weights" and len(sweep.albedos()) > 1
    return "shared" if ok else "independent"


def walk_groups(spec: "SimulationSpec") -> list[tuple[int, ...]]:
    """The media of each walk group in walk order, leader (largest albedo) last; one medium per
    group with independent walks.  Groups never span a (g, eta): media are albedo-fastest."""
    n = spec.n_media
    if walk_mode(spec) == "independent":
        return [(m,) for m in range(n)]
    albedos = spec.sweep.albedos()
    edges = spec.sweep.group_edges if spec.sweep.group_edges is not None else default_group_edges(spec)
    ranges = albedo_groups(albedos, edges)
    return [tuple(range(block + lo, block + hi)) for block in range(0, n, len(albedos)) for lo, hi in ranges]
