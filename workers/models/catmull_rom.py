"""Catmull-Rom splines on non-uniform nodes: weights, evaluation, integration, inversion and
sampling, as pbrt's tabulated BSSRDF uses them (numpy, torch-free).

On an interval [x_i, x_{i+1}] of width w the spline is the cubic Hermite interpolant of f_i,
f_{i+1} with end slopes taken from the neighbours (pbrt 3rd ed., sec. 8.6.2):

    d_i = w (f_{i+1} - f_{i-1}) / (x_{i+1} - x_{i-1})    (d_i = f_{i+1} - f_i at the first node)
    d_{i+1} = w (f_{i+2} - f_i) / (x_{i+2} - x_i)        (d_{i+1} = f_{i+1} - f_i at the last)

(slopes per unit t = (x - x_i) / w), p(t) = (2t^3 - 3t^2 + 1) f_i + (-2t^3 + 3t^2) f_{i+1}
+ (t^3 - 2t^2 + t) d_i + (t^3 - t^2) d_{i+1}, whose integral over the interval is
w ((f_i + f_{i+1}) / 2 + (d_i - d_{i+1}) / 12). Outside [x_0, x_{n-1}] the spline is 0.
Every function is pure; the sampler is vectorised over its uniforms.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "find_interval",
    "find_interval_pbrt",
    "catmull_rom_weights",
    "catmull_rom",
    "integrate_catmull_rom",
    "bin_integral_matrix",
    "invert_catmull_rom",
    "sample_catmull_rom_2d",
    "interval_slopes",
    "negative_mass",
]


def find_interval(nodes: np.ndarray, x) -> np.ndarray:
    """Index i in [0, n-2] with nodes[i] <= x (the last such), clamped: the interval holding x."""
    nodes = np.asarray(nodes, dtype=np.float64)
    return np.clip(np.searchsorted(nodes, x, side="right") - 1, 0, len(nodes) - 2)


def find_interval_pbrt(values, y) -> np.ndarray:
    """pbrt's ``FindInterval(size, [&](i) { return values[i] <= y; })``, elementwise in y: a
    binary search for the last i in [0, n-2] with values[i] <= y, clamped. On a monotone array
    it is :func:`find_interval`; on a non-monotone one (an interpolated CDF with a negative
    lobe) it lands where pbrt's sampler lands, which searchsorted does not promise."""
    values = np.asarray(values, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    n = len(values)
    first = np.ones(y.shape, dtype=np.int64)
    size = np.full(y.shape, n - 2, dtype=np.int64)
    while np.any(size > 0):
        half = size >> 1
        middle = np.minimum(first + half, n - 1)
        pred = (values[middle] <= y) & (size > 0)
        first = np.where(pred, middle + 1, first)
        size = np.where(pred, size - (half + 1), np.where(size > 0, half, 0))
    return np.clip(first - 1, 0, n - 2)


def catmull_rom_weights(nodes, x: float) -> tuple[int, np.ndarray] | None:
    """(offset, w[4]) with spline(x) = sum_k w[k] f[offset + k] for every value array f, or None
    if x is outside [nodes[0], nodes[-1]]. Weights of missing neighbours at the ends are folded
    into the interval's own nodes (their one-sided slopes), and w[k] = 0 there."""
    nodes = np.asarray(nodes, dtype=np.float64)
    n = len(nodes)
    if not nodes[0] <= x <= nodes[-1]:
        return None
    i = int(find_interval(nodes, x))
    x0, x1 = nodes[i], nodes[i + 1]
    t = (x - x0) / (x1 - x0)
    t2, t3 = t * t, t * t * t
    w = np.array([0.0, 2 * t3 - 3 * t2 + 1, -2 * t3 + 3 * t2, 0.0])
    h0, h1 = t3 - 2 * t2 + t, t3 - t2  # Hermite basis of the two slopes
    if i > 0:  # d_i = w (f_{i+1} - f_{i-1}) / (x_{i+1} - x_{i-1})
        s = h0 * (x1 - x0) / (x1 - nodes[i - 1])
        w[0] -= s
        w[2] += s
    else:  # d_0 = f_1 - f_0
        w[1] -= h0
        w[2] += h0
    if i + 2 < n:  # d_{i+1} = w (f_{i+2} - f_i) / (x_{i+2} - x_i)
        s = h1 * (x1 - x0) / (nodes[i + 2] - x0)
        w[1] -= s
        w[3] += s
    else:  # d_{n-1} = f_{n-1} - f_{n-2}
        w[1] -= h1
        w[2] += h1
    return i - 1, w


def catmull_rom(nodes, values, x) -> np.ndarray:
    """The spline through (nodes, values) at x (0 outside the node range), elementwise in x."""
    nodes, values = np.asarray(nodes, dtype=np.float64), np.asarray(values, dtype=np.float64)
    x = np.asarray(x, dtype=np.float64)
    i = find_interval(nodes, x)
    f0, f1, d0, d1 = interval_slopes(nodes, values, i)
    t = (x - nodes[i]) / (nodes[i + 1] - nodes[i])
    t2, t3 = t * t, t * t * t
    p = (2 * t3 - 3 * t2 + 1) * f0 + (-2 * t3 + 3 * t2) * f1 + (t3 - 2 * t2 + t) * d0 + (t3 - t2) * d1
    return np.where((x >= nodes[0]) & (x <= nodes[-1]), p, 0.0)


def interval_slopes(nodes, values, i) -> tuple[np.ndarray, ...]:
    """(f_i, f_{i+1}, d_i, d_{i+1}) of interval(s) i, slopes per unit t (module docstring).
    ``values`` may have leading axes (one spline per row); i indexes the last axis."""
    nodes, values = np.asarray(nodes, dtype=np.float64), np.asarray(values, dtype=np.float64)
    n = len(nodes)
    i = np.asarray(i)
    f0, f1 = values[..., i], values[..., i + 1]
    w = nodes[i + 1] - nodes[i]
    im1, ip2 = np.maximum(i - 1, 0), np.minimum(i + 2, n - 1)
    d0 = np.where(i > 0, w * (f1 - values[..., im1]) / (nodes[i + 1] - nodes[im1]), f1 - f0)
    d1 = np.where(i + 2 < n, w * (values[..., ip2] - f0) / (nodes[ip2] - nodes[i]), f1 - f0)
    return f0, f1, d0, d1


def integrate_catmull_rom(nodes, values) -> tuple[np.ndarray, np.ndarray]:
    """(total, cdf): the spline's integral over [x_0, x_{n-1}] and its running integral at the
    nodes (cdf[0] = 0, cdf[-1] = total, unnormalised), as pbrt's ``IntegrateCatmullRom``
    computes ``rhoEff`` and ``profileCDF``. ``values`` may have leading axes (one row per spline)."""
    nodes = np.asarray(nodes, dtype=np.float64)
    i = np.arange(len(nodes) - 1)
    f0, f1, d0, d1 = interval_slopes(nodes, values, i)
    pieces = ((f0 + f1) * 0.5 + (d0 - d1) / 12.0) * (nodes[1:] - nodes[:-1])
    cdf = np.concatenate([np.zeros(pieces.shape[:-1] + (1,)), np.cumsum(pieces, axis=-1)], axis=-1)
    return cdf[..., -1], cdf


def bin_integral_matrix(nodes, edges) -> np.ndarray:
    """B[j, k]: the integral over bin j = [edges[j], edges[j+1]) of the spline through the k-th
    unit vector, so that the spline through f integrates over bin j to (B f)_j. Exact (each
    interval's cubic integrated piecewise with its antiderivative); the spline is 0 outside
    [x_0, x_{n-1}], so a bin reaching past the last node counts only its part inside. Banded:
    bin j sees the nodes of the intervals it overlaps and their neighbours."""
    nodes, edges = np.asarray(nodes, dtype=np.float64), np.asarray(edges, dtype=np.float64)
    n = len(nodes)
    out = np.zeros((len(edges) - 1, n))
    unit = np.eye(n)
    for i in range(n - 1):
        f0, f1, d0, d1 = interval_slopes(nodes, unit, i)  # each [n]: one entry per unit vector
        a, b = nodes[i], nodes[i + 1]
        lo, hi = np.clip(edges[:-1], a, b), np.clip(edges[1:], a, b)
        for j in np.flatnonzero(hi > lo):
            upper, _ = _hermite_integral((hi[j] - a) / (b - a), f0, f1, d0, d1)
            lower, _ = _hermite_integral((lo[j] - a) / (b - a), f0, f1, d0, d1)
            out[j] += (b - a) * (upper - lower)
    return out


def _hermite_integral(t, f0, f1, d0, d1):
    """(F(t), f(t)): integral from 0 to t of the Hermite cubic per unit t, and the cubic itself."""
    F = t * (f0 + t * (0.5 * d0 + t * ((-2 * d0 - d1) / 3.0 + f1 - f0 + t * (0.25 * (d0 + d1) + 0.5 * (f0 - f1)))))
    f = f0 + t * (d0 + t * (-2 * d0 - d1 + 3 * (f1 - f0) + t * (d0 + d1 + 2 * (f0 - f1))))
    return F, f


def _solve_segment(target, f0, f1, d0, d1, tol: float = 1e-12, max_iter: int = 100) -> tuple[np.ndarray, np.ndarray]:
    """t in [0, 1] with F(t) = target (per unit t) by safeguarded Newton-bisection, vectorised;
    the first guess inverts the linear interpolant, as pbrt does. Returns (t, f(t))."""
    with np.errstate(invalid="ignore", divide="ignore"):
        lin = np.where(f0 != f1, (f0 - np.sqrt(np.maximum(0.0, f0 * f0 + 2 * target * (f1 - f0)))) / (f0 - f1),
                       target / f0)
    t = np.where(np.isfinite(lin), lin, 0.5)
    a, b = np.zeros_like(t), np.ones_like(t)
    done = np.zeros(t.shape, dtype=bool)
    f = np.zeros_like(t)
    for _ in range(max_iter):
        t = np.where((t >= a) & (t <= b), t, 0.5 * (a + b))  # Newton left the bracket: bisect
        F, f_new = _hermite_integral(t, f0, f1, d0, d1)
        f = np.where(done, f, f_new)
        done = done | (np.abs(F - target) < tol) | (b - a < tol)
        if done.all():
            break
        low = F < target
        a, b = np.where(done | ~low, a, t), np.where(done | low, b, t)
        with np.errstate(invalid="ignore", divide="ignore"):
            step = np.where(f_new != 0, (F - target) / f_new, np.inf)  # inf -> bisection next round
        t = np.where(done, t, t - step)
    return t, f


def invert_catmull_rom(nodes, values, y) -> np.ndarray:
    """x with spline(x) = y for a monotone increasing spline through (nodes, values) (pbrt's
    ``InvertCatmullRom``: where rhoEff is turned back into an albedo); y below values[0] gives
    nodes[0], above values[-1] gives nodes[-1]. Elementwise in y."""
    nodes, values = np.asarray(nodes, dtype=np.float64), np.asarray(values, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    i = find_interval(values, y)
    f0, f1, d0, d1 = interval_slopes(nodes, values, i)
    t, a, b = np.full(y.shape, 0.5), np.zeros(y.shape), np.ones(y.shape)
    for _ in range(100):
        t = np.where((t > a) & (t < b), t, 0.5 * (a + b))
        p = (2 * t**3 - 3 * t**2 + 1) * f0 + (-2 * t**3 + 3 * t**2) * f1 + (t**3 - 2 * t**2 + t) * d0 + (t**3 - t**2) * d1
        dp = (6 * t**2 - 6 * t) * f0 + (-6 * t**2 + 6 * t) * f1 + (3 * t**2 - 4 * t + 1) * d0 + (3 * t**2 - 2 * t) * d1
        if np.all((np.abs(p - y) < 1e-13) | (b - a < 1e-13)):
            break
        low = p < y
        a, b = np.where(low, t, a), np.where(low, b, t)
        with np.errstate(invalid="ignore", divide="ignore"):
            t = t - np.where(dp != 0, (p - y) / dp, np.inf)
    x = nodes[i] + t * (nodes[i + 1] - nodes[i])
    return np.where(y <= values[0], nodes[0], np.where(y >= values[-1], nodes[-1], x))


def sample_catmull_rom_2d(nodes1, nodes2, values, cdf, alpha: float, u) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Sample x2 with density proportional to the spline of ``values`` in both coordinates at
    x1 = alpha (pbrt's ``SampleCatmullRom2D``, with which ``TabulatedBSSRDF::Sample_Sr`` draws
    radii): ``values`` and ``cdf`` are [len(nodes1), len(nodes2)] (cdf the per-row running
    integral of :func:`integrate_catmull_rom`), both interpolated in x1 with the weights of
    :func:`catmull_rom_weights`; u in [0, 1) is scaled to the interpolated total, its interval is
    found on the interpolated cdf by pbrt's binary search (:func:`find_interval_pbrt`, also where
    that cdf is not monotone) and the spline's integral is inverted inside it.

    Returns (x2, f(x2), pdf(x2) = f / total), elementwise in u, or None if alpha is outside nodes1.
    """
    w = catmull_rom_weights(nodes1, alpha)
    if w is None:
        return None
    offset, weights = w
    rows = [(offset + k, weights[k]) for k in range(4) if weights[k] != 0.0]
    values, cdf = np.asarray(values, dtype=np.float64), np.asarray(cdf, dtype=np.float64)
    f_row = sum(wk * values[i] for i, wk in rows)
    c_row = sum(wk * cdf[i] for i, wk in rows)
    nodes2 = np.asarray(nodes2, dtype=np.float64)
    total = c_row[-1]
    target = np.asarray(u, dtype=np.float64) * total
    i = find_interval_pbrt(c_row, target)
    f0, f1, d0, d1 = interval_slopes(nodes2, f_row, i)
    width = nodes2[i + 1] - nodes2[i]
    t, f = _solve_segment((target - c_row[i]) / width, f0, f1, d0, d1)
    return nodes2[i] + width * t, f, f / total


def _cubic(t, a, b, c, d):
    return ((a * t + b) * t + c) * t + d


def _cubic_integral(t, a, b, c, d):
    return (((a / 4.0 * t + b / 3.0) * t + c / 2.0) * t + d) * t


def _negative_part(u, v, a, b, c, d):
    """Integral over [u, v] of min(p, 0) for a cubic p monotone on [u, v] (elementwise): the
    sign change, if any, is found by bisection (60 halvings: to rounding)."""
    pu, pv = _cubic(u, a, b, c, d), _cubic(v, a, b, c, d)
    lo, hi = u.copy(), v.copy()
    rising = pv > pu
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        below = (_cubic(mid, a, b, c, d) < 0) == rising  # the root is above mid
        lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
    r = 0.5 * (lo + hi)
    whole = _cubic_integral(v, a, b, c, d) - _cubic_integral(u, a, b, c, d)
    left = _cubic_integral(r, a, b, c, d) - _cubic_integral(u, a, b, c, d)
    right = whole - left
    return np.where((pu <= 0) & (pv <= 0), whole,
                    np.where((pu >= 0) & (pv >= 0), 0.0, np.where(pu < 0, left, right)))


def negative_mass(nodes, values) -> np.ndarray:
    """Integral of min(spline, 0) over [x_0, x_{n-1}] (<= 0): the negative lobes a Catmull-Rom
    spline of non-negative values can have where they fall steeply (pbrt's Pdf_Sr clamps them to
    0, and its sampler never lands there). Each interval's cubic is split at the zeros of its
    derivative into monotone pieces, each piece's sign change found by bisection and the
    negative part integrated with the cubic's antiderivative; vectorised. ``values`` may have
    leading axes (one row per spline)."""
    nodes, values = np.asarray(nodes, dtype=np.float64), np.asarray(values, dtype=np.float64)
    i = np.arange(len(nodes) - 1)
    f0, f1, d0, d1 = interval_slopes(nodes, values, i)
    # p(t) = a t^3 + b t^2 + c t + d, the Hermite form of the module docstring expanded
    a, b, c, d = 2 * f0 - 2 * f1 + d0 + d1, -3 * f0 + 3 * f1 - 2 * d0 - d1, d0, f0
    qa, qb = 3 * a, 2 * b
    with np.errstate(invalid="ignore", divide="ignore"):
        root = np.sqrt(np.maximum(qb * qb - 4 * qa * c, 0.0))
        real = qb * qb - 4 * qa * c >= 0
        crit = [np.where(qa != 0, (-qb + s * root) / (2 * qa), -c / qb) for s in (1.0, -1.0)]
    crit = [np.where(real & np.isfinite(t), np.clip(t, 0.0, 1.0), 1.0) for t in crit]
    cuts = np.sort(np.stack([np.zeros_like(a), crit[0], crit[1], np.ones_like(a)]), axis=0)
    pieces = sum(_negative_part(cuts[k], cuts[k + 1], a, b, c, d) for k in range(3))
    return np.sum(pieces * (nodes[1:] - nodes[:-1]), axis=-1)
