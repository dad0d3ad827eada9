"""Point values of a radial profile at pbrt's nodes from the bins centred on them (radial spacing
"pbrt"): each node read off its own bin and its neighbours' slope.

The exported table's node values are not these but the mass-keeping ones of
workers.exports.conserving (whose spline holds every bin's mass); these point values are what
that module compares with to state each node's error as a value of the profile.

pbrt's table needs the density in r of the exitance, f(r) = 2 pi r Sr(r), *at* its radius
nodes r_j; a Monte Carlo run measures the mass M_j = int f dr over bins. With spacing "pbrt"
(:func:`schema.bins.pbrt_radial_edges`) bin j >= 1 is [r_j / q, r_j q), q = sqrt(1.2), i.e.
symmetric about x_j = ln r_j in x = ln r with half-width h = ln(1.2) / 2. In x the profile is
F(x) = r f(r) and the bin average is F_bar_j = M_j / (2 h). If F is a local power law,
F = F(x_j) e^{b (x - x_j)} (f proportional to r^(b-1)), then exactly

    F_bar_j = F(x_j) sinh(b h) / (b h),   so   f(r_j) = (M_j / (2 h r_j)) (b h / sinh(b h)),

and the slope b follows from the neighbouring bins, b = (ln F_bar_{j+1} - ln F_bar_{j-1}) / (4 h)
(exact for a power law: the sinh factor cancels in the ratio); one-sided at the first and last
non-zero nodes. The factor is in (0, 1], so node values are >= 0 wherever the bins are. The
correction is 0.14 % for f = const (b = 1) and grows in the steep far tail.

Error this adds: the curvature c = (1/2) d^2 ln F / dx^2 that a power law ignores changes the
bin average by the relative amount ~ c h^2 / 3; it is estimated per node from second
differences of ln F_bar and reported as ``node_error`` (an estimate, same units as the value).
On photon-beam-diffusion profiles (tests/workers/test_export_nodes.py) the actual error is
within 1.5x that estimate plus 1e-6 of the profile maximum and below 1 % wherever the profile
exceeds 1e-4 of its maximum.

Node 0 (r = 0) is different: there is no bin centred on it in ln r, and the profile is not a
power law there. It gets the average density of its bin [0, w_0), w_0 = r_1 / q (0.00228 optical
radii), f_bar_0 = M_0 / w_0: an average over the bin, not f(0). The true f(0) = lim 2 pi r Rd(r)
is not 0: single scattering makes Rd grow like 1 / r towards the entry point (a first vertex at
depth z lights the point above it like z / d^3), so with sigma_t = 1, eta = 1 and normal
incidence f(0) = (albedo / 2) int_0^inf u du / (u^2 + 1)^(3/2) = albedo / 2 per unit power
entered, while multiple scattering (Rd finite at 0) adds nothing there; near 0 the slope
diverges logarithmically, f(r) ~ f(0) - albedo r ln(1 / r). (Photon beam diffusion has f(0) = 0:
its depth quadrature starts below the surface, so f ~ r there; a model artefact.) The bound that
applies: where f is monotone on [0, w_0), f_bar_0 lies between f(w_0) and f(0), so

    |f_bar_0 - f(0)| <= |f(0) - f(w_0)|,

and node 0 moves rhoEff and profileCDF by W_0 |f_bar_0 - f(0)|, W_0 = 0.53 w_0 its Catmull-Rom
integration weight (workers.exports.rho_eff). The reported ``node_error[0]`` is the linear-trend
estimate |f(r_1) - f_bar_0| w_0 / (2 (r_1 - w_0 / 2)) of |f_bar_0 - f(0)|; it misses the
logarithmic slope and falls short of the actual difference by up to ~2.5x on the exact single-
plus multiple-scattering profiles of tests/workers/test_export_nodes.py (there 0.2-1 % of f(0)).

Standard errors: se(M_j) times the same factor (the factor's own noise is second order and
neglected). A bin with no events (mass 0, NaN standard error) gives 0 with a NaN error; where a
neighbour has no positive mass the slope is unknown, the plain average is used and the error
estimate is NaN.
"""

from __future__ import annotations

import math

import numpy as np

from schema.bins import PBRT_RATIO, pbrt_radial_edges, pbrt_radius_nodes

__all__ = ["node_values", "node_scales", "check_pbrt_edges", "HALF_WIDTH"]

HALF_WIDTH = 0.5 * math.log(PBRT_RATIO)
"""h: half the width of a "pbrt" bin in ln r."""


def check_pbrt_edges(edges_optical: np.ndarray, rtol: float = 1e-9) -> bool:
    """Whether radial edges (optical radii) are exactly the "pbrt" spacing of their count."""
    edges = np.asarray(edges_optical, dtype=np.float64)
    if len(edges) < 3:
        return False
    return bool(np.allclose(edges, pbrt_radial_edges(len(edges) - 1), rtol=rtol, atol=0.0))


def _sinhc_inverse(y: np.ndarray) -> np.ndarray:
    """y / sinh(y), 1 at y = 0 (the series 1 - y^2/6 below 1e-4, where the quotient cancels)."""
    small = np.abs(y) < 1e-4
    safe = np.where(small, 1.0, y)
    return np.where(small, 1.0 - y * y / 6.0, safe / np.sinh(safe))


def node_values(masses, masses_stderr) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(f(r_j), se, node_error) at pbrt's nodes from bin masses M_j (fraction of power per
    bin, spacing "pbrt", n bins = n nodes), see the module docstring. f is per unit optical
    radius (pbrt's ``profile``)."""
    m = np.asarray(masses, dtype=np.float64)
    se = np.asarray(masses_stderr, dtype=np.float64)
    n = len(m)
    r = pbrt_radius_nodes(n)
    h = HALF_WIDTH
    w0 = r[1] / math.sqrt(PBRT_RATIO)
    f_bar = m / (2.0 * h)  # F_bar_j: mean of r f(r) over bin j in ln r (j >= 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        ln_f = np.where(f_bar > 0, np.log(f_bar), np.nan)
    slope = np.full(n, np.nan)
    curv = np.full(n, np.nan)
    if n >= 4:
        slope[2:-1] = (ln_f[3:] - ln_f[1:-2]) / (4.0 * h)
        # (1/2) d^2 ln F / dx^2 from second differences (centres 2h apart)
        curv[2:-1] = (ln_f[3:] - 2.0 * ln_f[2:-1] + ln_f[1:-2]) / (2.0 * (2.0 * h) ** 2)
        curv[1], curv[-1] = curv[2], curv[-2]  # the end nodes borrow their neighbour's curvature
    slope[1] = (ln_f[2] - ln_f[1]) / (2.0 * h)
    slope[-1] = (ln_f[-1] - ln_f[-2]) / (2.0 * h)
    known = np.isfinite(slope)
    factor = np.where(known, _sinhc_inverse(np.where(known, slope, 0.0) * h), 1.0)
    scale = np.concatenate([[1.0 / w0], factor[1:] / (2.0 * h * r[1:])])  # node value per unit bin mass
    values = m * scale
    stderr = se * scale
    error = np.abs(values * curv) * h * h / 3.0
    error = np.where(known & np.isfinite(curv), error, np.nan)
    # node 0: bin average over [0, w0) vs f(0), a linear trend up to the first node
    error[0] = abs(values[1] - values[0]) * w0 / (2.0 * (r[1] - 0.5 * w0))
    unresolved = ~(m > 0)
    values = np.where(unresolved, 0.0, values)
    error = np.where(unresolved, np.nan, error)
    return values, stderr, error


def node_scales(masses) -> np.ndarray:
    """s_j with node value f(r_j) = s_j M_j (:func:`node_values`; the slope factor in s_j comes
    from the neighbouring masses and is held fixed, as for the standard errors)."""
    m = np.asarray(masses, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        values, _se, _err = node_values(m, np.ones_like(m))
        return np.where(m > 0, values / m, 0.0)
