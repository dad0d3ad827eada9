"""Node values that keep the measured energy: the spline pbrt builds through them integrates over
every radial bin to that bin's measured mass.

pbrt interpolates a profile row between its radius nodes r_j with a Catmull-Rom spline and takes
rhoEff and profileCDF as that spline's integral (workers.models.catmull_rom). The spline through node
values f integrates over bin j (spacing "pbrt": bin j >= 1 is [r_j / q, r_j q), q = sqrt(1.2),
bin 0 is [0, r_1 / q)) to (B f)_j, with B = :func:`workers.models.catmull_rom.bin_integral_matrix`, a
banded matrix (bin j sees nodes j-2 .. j+2). The node values are the solution of

    B f = M        (M_j the measured mass of bin j, per unit power entered),

so the spline holds exactly the measured mass of every bin and rhoEff = sum_j M_j: the measured
total within the last node, with no discretisation bias. (Values read off the bins one at a
time, mass / width, put 0.07-0.14 % less under the spline than the bins hold, because the
spline's shape between nodes is not the profile's.) In-between values are what the spline
makes of them; the node value itself is not the profile's value at r_j but the one that gives
the spline the right bin masses.

The last bin reaches past the last node, where pbrt's spline is 0: its equation keeps only the
part of its mass inside, the fraction phi = 1 / (1 + e^{b h}) of a local power law F(ln r) ~
e^{b x} (h = ln(1.2) / 2, b from the last two bins; 1/2 for b = 0), and the rest is counted
with the mass beyond the table (``beyond``).

Bins without events (their mass is 0 and their standard error NaN) must not make the spline
dip: a Catmull-Rom spline that falls to 0 at a node between positive neighbours, or ends in a
run of zeros, always goes negative next to it. So:

* a run of empty bins between two bins with events is pooled with the outer one (one equation:
  the run and that bin hold its mass), and the run's nodes lie on the straight line (in r)
  between the neighbouring measured nodes; a run at the start takes the first measured node's
  value;
* beyond the last bin with events L the bins are pooled with bin L, and the nodes continue
  geometrically, f_{L+k} = TAIL_RATIO^k f_L: a geometric tail with ratio rho >= 0.18 per
  node has non-negative Bernstein coefficients on every interval (f_i + d_i / 3 >= 0 and
  f_{i+1} - d_{i+1} / 3 >= 0), so the spline stays >= 0 to the last node.

* a measured bin whose node would make the spline dip below 0 anywhere (a lone heavy event the
  spline overshoots around, a lone light one, a fall steeper than the spline can follow) is
  pooled the same way, one at a time from the inside out until no interval dips
  (:func:`interval_minima`): of the measured nodes shaping the first dipping interval, the one
  whose bin density stands out most (in log) from its measured neighbours'.  Where the dipping
  interval lies in a run that holds empty bins, the measured node the run starts from is tried
  as well and the one leaving less negative mass is pooled: single photons in the tiny innermost
  bins make such a node a spike that the run's straight line carries outward.

These nodes are modelled, not measured: their ``error`` is their whole value. The mass stays
the measured mass of the pooled bins: each group (a measured bin and the pooled bins before
it; the last also the tail) holds its mass, so rhoEff is still the sum of all bin masses.

Errors. f = K M is linear in the bin masses (K = T (P B T)^-1 P with the pooling P and the
node map T above), so the node covariance is K Sigma K^T for the bins' covariance Sigma (exit
tally: one exit per photon, Sigma_jk = se_j^2 [j = k] - M_j M_k / (N - 1) [j != k] in photon units,
workers.exports.rho_eff; other estimators: the diagonal, their bins' covariance is not stored),
and rhoEff = c . M with c = W K, W the Catmull-Rom integration weights; c_j = 1 for every bin
but the last (phi). ``error`` states the remaining discretisation error of each node as a
point value: |f_j - f_point_j| + e_point_j, f_point the power-law reading of the bins
(workers.exports.nodes) and e_point its curvature estimate; it contains noise of the size of
the node's standard error.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from schema.bins import pbrt_radial_edges, pbrt_radius_nodes
from workers.models.catmull_rom import bin_integral_matrix, integrate_catmull_rom, interval_slopes, negative_mass

from .nodes import HALF_WIDTH, node_values

__all__ = ["NodeRow", "conserving_nodes", "bin_matrix", "interval_minima", "TAIL_RATIO"]

TAIL_RATIO = 0.25
"""Ratio of consecutive nodes beyond the last bin with events (>= 0.178, see the docstring)."""


@dataclass(frozen=True)
class NodeRow:
    """One profile row: node values, their covariance and stated error, the coefficients c with
    rhoEff = c . M, the mass of the last bin outside the last node, and which nodes are modelled."""

    values: np.ndarray
    cov: np.ndarray
    error: np.ndarray
    coefficients: np.ndarray
    beyond: float
    modelled: np.ndarray

    @property
    def stderr(self) -> np.ndarray:
        return np.sqrt(np.maximum(np.diag(self.cov), 0.0))

    @property
    def rho_eff_stderr(self) -> float:
        """sqrt(c Sigma c^T) = sqrt(W Cov(f) W^T): rhoEff's standard error from the node covariance."""
        w = integration_weights_of(len(self.values))
        return float(math.sqrt(max(w @ self.cov @ w, 0.0)))


@functools.lru_cache(maxsize=8)
def bin_matrix(count: int) -> np.ndarray:
    """B for ``count`` pbrt nodes and their bins (read-only)."""
    b = bin_integral_matrix(pbrt_radius_nodes(count), pbrt_radial_edges(count))
    b.setflags(write=False)
    return b


@functools.lru_cache(maxsize=8)
def integration_weights_of(count: int) -> np.ndarray:
    w, _ = integrate_catmull_rom(pbrt_radius_nodes(count), np.eye(count))
    w.setflags(write=False)
    return w


def inside_fraction(masses: np.ndarray) -> float:
    """phi = 1 / (1 + e^{b h}): the part of the last bin inside the last node for F ~ e^{b x}."""
    a, b = masses[-2], masses[-1]
    slope = math.log(b / a) / (2.0 * HALF_WIDTH) if a > 0 and b > 0 else 0.0
    return 1.0 / (1.0 + math.exp(min(slope * HALF_WIDTH, 700.0)))


def _structure(resolved: np.ndarray, nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T [n, K], P [K, n]): node values f = T g from the K measured nodes g, and the pooling
    of bins into K groups (each measured bin with the empty run before it; the empty tail with
    the last)."""
    n = len(resolved)
    anchors = np.flatnonzero(resolved)
    T = np.zeros((n, len(anchors)))
    P = np.zeros((len(anchors), n))
    prev = None
    for k, a in enumerate(anchors):
        T[a, k] = 1.0
        start = 0 if prev is None else prev + 1
        P[k, start:a + 1] = 1.0
        for j in range(start, a):  # the empty run before anchor a
            if prev is None:
                T[j, k] = 1.0
            else:
                s = (nodes[a] - nodes[j]) / (nodes[a] - nodes[prev])
                T[j, k - 1], T[j, k] = s, 1.0 - s
        prev = a
    last = anchors[-1]
    P[-1, last + 1:] = 1.0
    T[last + 1:, -1] = TAIL_RATIO ** np.arange(1, n - last)
    return T, P


def interval_minima(nodes, values) -> np.ndarray:
    """The minimum of the spline over each interval (exact: the Hermite cubic at its ends and at
    the real zeros of its derivative inside)."""
    i = np.arange(len(nodes) - 1)
    f0, f1, d0, d1 = interval_slopes(nodes, values, i)
    # p(t) = a t^3 + b t^2 + d0 t + f0, p'(t) = 3 a t^2 + 2 b t + d0
    a, b = 2 * f0 - 2 * f1 + d0 + d1, -3 * f0 + 3 * f1 - 2 * d0 - d1
    low = np.minimum(f0, f1)
    qa, qb, qc = 3 * a, 2 * b, d0
    with np.errstate(invalid="ignore", divide="ignore"):
        disc = np.sqrt(qb * qb - 4 * qa * qc)
        roots = [np.where(qa != 0, (-qb + s * disc) / (2 * qa), -qc / qb) for s in (1.0, -1.0)]
    for t in roots:
        inside = np.isfinite(t) & (t > 0) & (t < 1)
        tt = np.where(inside, t, 0.0)
        p = ((a * tt + b) * tt + d0) * tt + f0
        low = np.where(inside, np.minimum(low, p), low)
    return low


def _solve(m: np.ndarray, anchored: np.ndarray, nodes: np.ndarray, scale: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(K, f): f = K M with the nodes ``anchored`` free and the others modelled (module
    docstring); ``m`` has 0 in bins without events."""
    T, P = _structure(anchored, nodes)
    K = T @ np.linalg.solve(P @ bin_matrix(len(m)) @ T, P) * scale
    return K, K @ m


def _next_to_pool(values: np.ndarray, anchored: np.ndarray, m: np.ndarray, edges: np.ndarray) -> tuple[int, ...] | None:
    """The measured nodes to try pooling next, or None when the spline is >= 0 everywhere. The first
    interval i that dips below 0 (by more than rounding) is shaped by nodes i-1 .. i+2; of the
    measured ones, the bin whose density M_j / width_j stands out most from its measured
    neighbours' (in log, against the mean of the nearest measured bin on each side) is pooled:
    a lone heavy event (a spike the spline overshoots around) or a lone light one (a hole).
    Second, where interval i lies in a run that holds bins without events: the measured node the
    run starts from (:func:`_pool_one` keeps the better of the two).  Runs of pooled measured
    bins alone (a smooth profile's far tail) are left to the first rule."""
    dips = np.flatnonzero(interval_minima(pbrt_radius_nodes(len(values)), values) < -1e-12 * np.max(np.abs(values)))
    if not dips.size:
        return None
    i = int(dips[0])
    anchors = np.flatnonzero(anchored)
    ln_density = np.log(np.where(anchored, m, 1.0) / np.diff(edges))
    best, worst = None, -1.0
    for j in range(max(i - 1, 0), min(i + 3, len(values))):
        if not anchored[j]:
            continue
        k = int(np.searchsorted(anchors, j))
        around = [ln_density[anchors[k - 1]]] if k > 0 else []
        around += [ln_density[anchors[k + 1]]] if k + 1 < len(anchors) else []
        deviation = abs(ln_density[j] - np.mean(around)) if around else 0.0
        if deviation > worst:
            best, worst = j, deviation
    if best is None:
        after, before = np.flatnonzero(anchored[i + 1:]), np.flatnonzero(anchored[:i])
        best = int(i + 1 + after[0]) if after.size else int(before[-1])
    start = anchors[anchors < i]
    if start.size and start[-1] < i - 1 and start[-1] != best:
        s = int(start[-1])
        end = anchors[anchors > s]
        if np.any(m[s + 1 : int(end[0]) if end.size else len(m)] == 0):  # the run holds bins without events
            return best, s
    return (best,)


def _pool_one(m, anchored, nodes, scale, values):
    """Pool the next node (:func:`_next_to_pool`); returns (anchored, K, values) after it, or None
    when the spline is >= 0 everywhere.  Where the dip lies in a pooled run, the measured node the
    run starts from is tried too, and whichever leaves the spline less negative mass is pooled:
    the run's straight line carries that node's value out to the dip, so a spike there (single
    photons in the tiny innermost bins) would otherwise push the dip outward one pooled node at a
    time until one node held the whole row."""
    candidates = _next_to_pool(values, anchored, m, pbrt_radial_edges(len(m)))
    if candidates is None:
        return None
    tried = []
    for c in candidates:
        trial = anchored.copy()
        trial[c] = False
        K, v = _solve(m, trial, nodes, scale)
        tried.append((-negative_mass(nodes, v), trial, K, v))  # negative_mass is <= 0
    _, trial, K, v = min(tried, key=lambda t: t[0])  # the first on a tie: the spike rule's choice
    return trial, K, v


def conserving_nodes(masses, masses_stderr, photons: int | None = None) -> NodeRow:
    """The node values of the module docstring from bin masses M_j and their standard errors
    (NaN: no events). ``photons`` given: the exit tally's covariance (one exit per photon);
    None: the bins are taken as independent. Measured nodes whose values would make the spline
    dip below 0 anywhere (:func:`interval_minima`) are pooled like
    empty bins, one at a time from the inside out, until the spline is >= 0 or one node is left."""
    m = np.asarray(masses, dtype=np.float64)
    se = np.asarray(masses_stderr, dtype=np.float64)
    n = len(m)
    resolved = np.isfinite(se) & (m > 0)
    if not resolved.any():
        nan = np.full(n, np.nan)
        return NodeRow(np.zeros(n), np.full((n, n), np.nan), nan, np.zeros(n), 0.0, np.ones(n, dtype=bool))
    nodes = pbrt_radius_nodes(n)
    phi = inside_fraction(m) if resolved[-1] else 1.0
    scale = np.ones(n)
    scale[-1] = phi
    m = np.where(resolved, m, 0.0)
    anchored = resolved.copy()
    K, values = _solve(m, anchored, nodes, scale)
    while anchored.sum() > 1:
        pooled = _pool_one(m, anchored, nodes, scale, values)
        if pooled is None:
            break
        anchored, K, values = pooled
    se0 = np.where(np.isfinite(se), se, 0.0)
    sigma = np.diag(se0 * se0)
    if photons is not None:
        sigma = sigma - (np.outer(m, m) - np.diag(m * m)) / (photons - 1)  # -M_j M_k / (N - 1), j != k
    cov = K @ sigma @ K.T
    coefficients = integration_weights_of(n) @ K
    modelled = ~anchored
    point, _point_se, point_err = node_values(m, se)
    gap = np.abs(values - point)
    error = np.where(modelled, np.abs(values), gap + np.where(np.isfinite(point_err), point_err, gap))
    beyond = (1.0 - phi) * m[-1] if resolved[-1] else 0.0
    return NodeRow(values, cov, error, coefficients, float(beyond), modelled)
