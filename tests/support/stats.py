"""Statistical assertions for the sampler tests: Pearson chi-square goodness of fit and z-scores.

The chi-square test follows the design of mitsuba3's ``chi2.py``: the samples are histogrammed
over fixed cells, the expected probability mass of every cell is obtained *independently of the
sampler* by integrating the density numerically (scipy.integrate.quad), cells whose expected
count is below 5 are pooled so that the chi-square approximation holds, and the null hypothesis
"the samples follow the density" is rejected only when

    p-value < 1 - (1 - alpha)^(1 / n_tests)          (Sidak correction, ~ alpha / n_tests)

with alpha = 1e-4 by default and ``n_tests`` the number of tests in the family (e.g. one per
value of g), so a family of tests has overall false-alarm rate alpha while a real deviation of
the sampler (a wrong formula, a sign, a missing Jacobian) gives p-values many orders of
magnitude smaller.  All tests use fixed seeds, so the outcome is reproducible.

Samples that fall outside the histogram range go to one extra *remainder* cell whose expected
mass is 1 minus the mass of the cells, so a sampler that leaks mass out of its domain fails too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy import integrate
from scipy import stats as sps

__all__ = [
    "ALPHA",
    "MIN_EXPECTED",
    "Chi2Result",
    "sidak_level",
    "cell_masses",
    "histogram",
    "chi2_test",
    "assert_chi2",
    "assert_samples_match_pdf",
    "z_score",
    "z_threshold",
    "assert_z",
    "assert_mean",
]

ALPHA = 1e-4
"""Family-wise false-alarm probability of a statistical test."""

MIN_EXPECTED = 5.0
"""Cells with fewer expected samples are pooled (Pearson's rule of thumb)."""


def sidak_level(alpha: float, n_tests: int) -> float:
    """Per-test significance level so that n_tests independent tests reject with probability alpha."""
    if n_tests < 1:
        raise ValueError(f"n_tests must be >= 1, got {n_tests}")
    return -math.expm1(math.log1p(-alpha) / n_tests)


def cell_masses(pdf: Callable[[float], float], edges, points=None, epsabs: float = 1e-13) -> np.ndarray:
    """Probability mass of every cell [edges[k], edges[k+1]] of a 1-D density, by adaptive quadrature.

    ``pdf`` is a plain function of one float.  ``points``: optional abscissae where the density
    is sharply peaked (passed to quad for the cells that contain them).
    """
    edges = np.asarray(edges, dtype=np.float64)
    out = np.empty(len(edges) - 1)
    for k, (a, b) in enumerate(zip(edges[:-1], edges[1:])):
        inside = None if points is None else [p for p in points if a < p < b] or None
        out[k], _ = integrate.quad(pdf, a, b, points=inside, epsabs=epsabs, epsrel=1e-11, limit=200)
    return out


def histogram(samples, edges) -> np.ndarray:
    """Counts of samples in the cells [edges[k], edges[k+1]) (last cell closed), as float64.

    Non-finite samples and samples outside [edges[0], edges[-1]] are not counted here; see
    :func:`chi2_test`, which puts them in the remainder cell.
    """
    x = np.asarray(samples, dtype=np.float64).ravel()
    counts, _ = np.histogram(x[np.isfinite(x)], bins=np.asarray(edges, dtype=np.float64))
    return counts.astype(np.float64)


@dataclass
class Chi2Result:
    """Outcome of :func:`chi2_test`; ``message`` explains a rejection."""

    statistic: float
    dof: int
    p_value: float
    level: float
    cells_in: int
    cells_out: int
    passed: bool
    message: str

    def __str__(self) -> str:
        return (
            f"chi2 = {self.statistic:.2f}, dof = {self.dof}, p = {self.p_value:.3g} (reject below "
            f"{self.level:.3g}); {self.cells_in} cells pooled into {self.cells_out}. {self.message}"
        )


def _pool(observed: np.ndarray, expected: np.ndarray, min_expected: float) -> tuple[np.ndarray, np.ndarray]:
    """Merge cells, in increasing order of expected count, until each has >= min_expected.

    A leftover group that never reaches the threshold joins the last completed group (or forms
    the only group).
    """
    order = np.argsort(expected, kind="stable")
    obs_out: list[float] = []
    exp_out: list[float] = []
    acc_o = acc_e = 0.0
    for i in order:
        acc_o += observed[i]
        acc_e += expected[i]
        if acc_e >= min_expected:
            obs_out.append(acc_o)
            exp_out.append(acc_e)
            acc_o = acc_e = 0.0
    if acc_e > 0.0 or acc_o > 0.0:
        if exp_out:
            obs_out[-1] += acc_o
            exp_out[-1] += acc_e
        else:
            obs_out.append(acc_o)
            exp_out.append(acc_e)
    return np.asarray(obs_out), np.asarray(exp_out)


def chi2_test(
    counts,
    masses,
    n_samples: int,
    n_tests: int = 1,
    alpha: float = ALPHA,
    min_expected: float = MIN_EXPECTED,
) -> Chi2Result:
    """Pearson chi-square test of histogram ``counts`` against expected cell ``masses``.

    ``counts``: observed counts per cell (any shape, flattened; 2-D histograms work as is).
    ``masses``: expected probability per cell, same shape, summing to at most 1.  The missing
    mass 1 - sum(masses) and the missing count n_samples - sum(counts) form a remainder cell
    (samples outside the cells).  Degrees of freedom: pooled cells - 1.
    """
    obs = np.asarray(counts, dtype=np.float64).ravel()
    mass = np.asarray(masses, dtype=np.float64).ravel()
    if obs.shape != mass.shape:
        raise ValueError(f"counts {obs.shape} and masses {mass.shape} differ in shape")
    total_mass = float(mass.sum())
    # Quadrature error of the masses is ~1e-11; anything well above is a broken reference.
    if total_mass > 1.0 + 1e-7 or np.any(mass < 0):
        raise ValueError(f"cell masses must be >= 0 and sum to <= 1, got sum {total_mass!r}")
    rest_obs = n_samples - float(obs.sum())
    rest_mass = max(0.0, 1.0 - total_mass)
    obs = np.append(obs, rest_obs)
    exp = np.append(mass, rest_mass) * n_samples
    level = sidak_level(alpha, n_tests)

    # A sample where the density says none can be is an outright rejection (the remainder cell
    # included: a sampler leaking outside its domain).  "None" = expected count below 1e-9.
    impossible = (exp < 1e-9) & (obs > 0)
    if np.any(impossible):
        cells = np.flatnonzero(impossible)
        return Chi2Result(math.inf, 0, 0.0, level, len(obs), 0, False,
                          f"{int(obs[cells].sum())} samples in cells of zero expected mass {cells.tolist()[:10]}"
                          f" (index {len(obs) - 1} is the out-of-range remainder)")
    keep = exp >= 1e-9
    pooled_obs, pooled_exp = _pool(obs[keep], exp[keep], min_expected)
    dof = len(pooled_obs) - 1
    if dof < 1:
        return Chi2Result(math.nan, dof, math.nan, level, len(obs), len(pooled_obs), False,
                          "fewer than 2 cells after pooling: refine the cells or draw more samples")
    stat = float(np.sum((pooled_obs - pooled_exp) ** 2 / pooled_exp))
    p_value = float(sps.chi2.sf(stat, dof))
    passed = bool(np.isfinite(p_value) and p_value >= level)
    msg = "" if passed else _worst_cells(obs, exp)
    return Chi2Result(stat, dof, p_value, level, len(obs), len(pooled_obs), passed, msg)


def _worst_cells(obs: np.ndarray, exp: np.ndarray, n: int = 5) -> str:
    """The cells with the largest Pearson residuals, for the failure message."""
    resid = (obs - exp) / np.sqrt(np.maximum(exp, 1e-300))
    worst = np.argsort(-np.abs(resid))[:n]
    return "Worst cells (index: observed vs expected): " + ", ".join(
        f"{i}: {obs[i]:.0f} vs {exp[i]:.1f}" for i in worst
    )


def assert_chi2(counts, masses, n_samples: int, n_tests: int = 1, alpha: float = ALPHA, what: str = "") -> Chi2Result:
    """:func:`chi2_test` that raises AssertionError with the statistics on rejection."""
    res = chi2_test(counts, masses, n_samples, n_tests=n_tests, alpha=alpha)
    assert res.passed, f"{what}: samples do not follow the expected distribution: {res}"
    return res


def assert_samples_match_pdf(
    samples, pdf: Callable[[float], float], edges, n_tests: int = 1, alpha: float = ALPHA, points=None, what: str = ""
) -> Chi2Result:
    """Histogram 1-D ``samples`` over ``edges`` and chi-square test them against ``pdf``.

    The expected masses come from integrating ``pdf`` over each cell with scipy, never from the
    sampler.  Non-finite samples count as out of range (and so fail unless mass is missing).
    """
    samples = np.asarray(samples, dtype=np.float64).ravel()
    counts = histogram(samples, edges)
    masses = cell_masses(pdf, edges, points=points)
    return assert_chi2(counts, masses, samples.size, n_tests=n_tests, alpha=alpha, what=what)


def z_score(estimate: float, expected: float, std_err: float) -> float:
    """(estimate - expected) / std_err."""
    return (estimate - expected) / std_err


def z_threshold(n_tests: int, alpha: float = ALPHA) -> float:
    """|z| above which a family of n_tests two-sided normal checks rejects (Sidak level)."""
    return float(sps.norm.isf(0.5 * sidak_level(alpha, n_tests)))


def assert_z(estimate: float, expected: float, std_err: float, n_sigma: float = 4.0, what: str = "") -> float:
    """Assert |estimate - expected| <= n_sigma * std_err (4 sigma: false alarm ~6e-5 per check)."""
    if not (std_err > 0 and math.isfinite(std_err)):
        raise ValueError(f"{what}: standard error must be positive and finite, got {std_err}")
    z = z_score(estimate, expected, std_err)
    assert abs(z) <= n_sigma, (
        f"{what}: estimate {estimate:.6g} differs from {expected:.6g} by {z:+.2f} standard errors "
        f"(std err {std_err:.3g}, allowed {n_sigma})"
    )
    return z


def assert_mean(samples, expected: float, std: float | None = None, n_sigma: float = 4.0, what: str = "") -> float:
    """Sample mean equals ``expected`` within n_sigma standard errors.

    ``std``: the population standard deviation if known in closed form (preferred: then the
    check does not rely on the sample's own spread); else the sample standard deviation.
    """
    x = np.asarray(samples, dtype=np.float64).ravel()
    sd = float(np.std(x, ddof=1)) if std is None else float(std)
    return assert_z(float(x.mean()), expected, sd / math.sqrt(x.size), n_sigma=n_sigma, what=what)
