"""Shared fixtures of the test suite.

The walk tests run the eager walk (BSSRDF_COMPILE=0): torch.compile costs 30-60 s per step
function, more than the statistics themselves.  tests/workers/test_walk_determinism.py runs the compiled
path once, in a subprocess, under the ``slow`` mark.
"""

from __future__ import annotations

import os

os.environ.setdefault("BSSRDF_COMPILE", "0")
if os.environ.get("PYTEST_XDIST_WORKER"):  # pytest -n: one process per core already, so one torch thread each
    import torch

    torch.set_num_threads(1)

import math  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402
from scipy import stats as sps  # noqa: E402

from tests.support.stats import ALPHA, sidak_level  # noqa: E402


class WalkStats:
    """Error-bar arithmetic for tests of Monte Carlo results that carry their own standard errors.

    A reported standard error is estimated from K independent batches, so (estimate - truth) / se
    follows Student's t with K - 1 degrees of freedom, not the normal law; the cuts below use it.
    Family-wise false-alarm probability ALPHA (1e-4) with the Sidak correction over n_tests.
    """

    alpha = ALPHA

    @staticmethod
    def z_limit(n_tests: int = 1, dof: float = math.inf, alpha: float = ALPHA) -> float:
        """Two-sided |z| cut for n_tests checks of t-distributed z-scores (dof = batches - 1)."""
        level = sidak_level(alpha, n_tests)
        return float(sps.norm.isf(level / 2) if math.isinf(dof) else sps.t.isf(level / 2, dof))

    @staticmethod
    def dof(result, name: str | None = None) -> int:
        """Degrees of freedom of a merged result's standard errors (units - 1: photons - 1 or
        batches - 1, workers.fold.tally): of quantity `name`, or the fewest of any estimator."""
        if name is not None:
            return result.dof(name)
        return min(result.dof(f"{e}/Rd") for e in result.estimators)

    @staticmethod
    def z(a, se_a, b, se_b=0.0) -> np.ndarray:
        """(a - b) / sqrt(se_a^2 + se_b^2), elementwise: a and b independent estimates (or b exact)."""
        a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
        return (a - b) / np.sqrt(np.asarray(se_a, dtype=np.float64) ** 2 + np.asarray(se_b, dtype=np.float64) ** 2)

    @staticmethod
    def t_variance(dof: float) -> float:
        """Variance of Student's t (of z-scores whose standard errors have `dof` degrees of freedom)."""
        return 1.0 if math.isinf(dof) else dof / (dof - 2.0)

    @classmethod
    def chi2_band(cls, n: int, dof: float = math.inf, alpha: float = ALPHA, n_tests: int = 1) -> tuple[float, float]:
        """Two-sided band of sum z^2 over n independent z-scores with unit spread.

        sum z^2 is chi-square with n degrees of freedom for normal z; t-distributed z (estimated
        standard errors) have variance dof / (dof - 2), which scales the band.
        """
        level = sidak_level(alpha, n_tests)
        scale = cls.t_variance(dof)
        return float(sps.chi2.ppf(level / 2, n) * scale), float(sps.chi2.isf(level / 2, n) * scale)

    @classmethod
    def assert_unit_spread(cls, z, dof: float, what: str, n_tests: int = 1) -> float:
        """Assert sum z^2 of independent z-scores lies in its chi-square band; returns sum z^2."""
        z = np.asarray(z, dtype=np.float64).ravel()
        assert np.all(np.isfinite(z)), f"{what}: non-finite z-scores {z}"
        lo, hi = cls.chi2_band(len(z), dof, n_tests=n_tests)
        q = float(np.sum(z * z))
        print(f"{what}: sum z^2 = {q:.2f} over {len(z)}, band [{lo:.2f}, {hi:.2f}]")
        assert lo <= q <= hi, (
            f"{what}: sum z^2 = {q:.2f} over {len(z)} bins outside the band [{lo:.2f}, {hi:.2f}] "
            f"(alpha {cls.alpha:g}); z = {np.array2string(z, precision=2)}"
        )
        return q

    @classmethod
    def assert_within(cls, z, dof: float, what: str, n_tests: int | None = None) -> float:
        """Assert every |z| is below the Sidak-corrected t cut for the family; returns max |z|."""
        z = np.asarray(z, dtype=np.float64).ravel()
        n = len(z) if n_tests is None else n_tests
        lim = cls.z_limit(n, dof)
        assert np.all(np.isfinite(z)), f"{what}: non-finite z-scores {z}"
        worst = float(np.max(np.abs(z)))
        print(f"{what}: z = {np.array2string(z, precision=2)}, max |z| {worst:.2f} <= {lim:.2f}")
        assert worst <= lim, f"{what}: max |z| = {worst:.2f} exceeds {lim:.2f}; z = {np.array2string(z, precision=2)}"
        return worst


@pytest.fixture(scope="session")
def walk_stats() -> type[WalkStats]:
    """The error-bar helpers (:class:`WalkStats`)."""
    return WalkStats


def make_walk_spec(
    sigma_a: float,
    sigma_s: float,
    *,
    g: float = 0.0,
    eta: float = 1.0,
    n_r: int = 8,
    max_mm: float = 4.0,
    spacing: str = "linear",
    n_theta: int = 1,
    n_cos: int = 1,
    n_phi: int = 1,
    **fields,
):
    """A SimulationSpec of a one-channel medium with a compact bin layout; `fields` override the rest."""
    from schema import SimulationSpec

    data = {
        "name": fields.pop("name", "walk-test"),
        "medium": {"sigma_a": sigma_a, "sigma_s": sigma_s, "g": g, "eta": eta},
        "bins": {
            "radial": {"count": n_r, "max_mm": max_mm, "spacing": spacing},
            "theta_s": {"count": n_theta},
            "cos_theta_o": {"count": n_cos},
            "phi_o": {"count": n_phi},
        },
    }
    if "bins" in fields:
        data["bins"] = fields.pop("bins")
    data.update(fields)
    return SimulationSpec.model_validate(data)


@pytest.fixture(scope="session")
def walk_spec():
    """Factory of compact walk specs (:func:`make_walk_spec`)."""
    return make_walk_spec
