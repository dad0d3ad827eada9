"""The standard error of pbrt's rhoEff: the Catmull-Rom integral of the node values.

rhoEff is linear in the node values, rhoEff = sum_j W_j f_j, with W_j the integral of the
spline's j-th cardinal function (:func:`integration_weights`, what ``IntegrateCatmullRom`` sums),
and the node values are linear in the bin masses, f = K M (workers.exports.conserving), so
rhoEff = sum_j c_j M_j with c = W K: 1 on every bin (the spline holds each bin's mass), the
inner fraction on the last (its part beyond the last node is left out). Its variance needs the
covariance of the bin masses.

Exit tally (``exits``): a photon leaves once, so its entries x_pj (its weight in bin j, all
components) are non-zero in at most one bin. For such entries the per-photon second moments of
any combination y_p = sum_j c_j x_pj follow from the bins' own: mean(y^2) = sum_j c_j^2 mean(x_j^2)
and mean(x_j^2) = (N - 1) se_j^2 + m_j^2 (the tally's photon units, workers.fold.tally), hence the
exact photon-unit standard error

    se(c . m)^2 = sum_j c_j^2 se_j^2 + (sum_j c_j^2 m_j^2 - (c . m)^2) / (N - 1)     (*)

(:func:`disjoint_stderr`): the second term is the bins' negative covariance, -m_j m_k / (N - 1)
for j != k. With c_j = 1 over every bin and the part beyond r_max it is the tally's own se(Rd).

Other estimators: the connection samples of one photon (``hybrid``: the first vertex connects
to every bin; ``connections``: every vertex) reach many bins, and their covariance is not stored
(only per-bin and per-total moments are). There ``rhoEffStderr`` is the standard error of the
measured total Rd / (1 - R_spec) (formed with that covariance by the tally), which rhoEff equals
up to the part beyond the last node (``rhoBeyondRmax``).
"""

from __future__ import annotations

import numpy as np

from workers.models.catmull_rom import integrate_catmull_rom

__all__ = ["integration_weights", "disjoint_stderr", "DISJOINT_ESTIMATORS", "MEANING"]

DISJOINT_ESTIMATORS = ("exits",)
"""Estimators whose photons contribute to one bin at most (formula (*) is exact)."""

MEANING = {
    "disjoint": "standard error of rhoEff itself: sqrt(W Cov(f) W^T), the node covariance (the bins' covariance of "
                "one exit per photon through the linear solve) through the Catmull-Rom integration weights "
                "(workers/exports/rho_eff.py, workers/exports/conserving.py)",
    "total": "standard error of the measured total Rd / (1 - R_spec), which rhoEff equals up to rhoBeyondRmax (the "
             "bins' covariance of this estimator is not stored; workers/exports/rho_eff.py)",
}
"""The ``rhoEffStderrMeaning`` of a table, by whether its estimator's bins are disjoint per photon."""


def integration_weights(nodes) -> np.ndarray:
    """W_j: the Catmull-Rom integral over the nodes of the spline through the j-th unit vector,
    so that :func:`workers.models.catmull_rom.integrate_catmull_rom` of f is sum_j W_j f_j."""
    nodes = np.asarray(nodes, dtype=np.float64)
    total, _cdf = integrate_catmull_rom(nodes, np.eye(len(nodes)))
    return total


def disjoint_stderr(coef, mean, stderr, photons: int) -> float:
    """Formula (*): the standard error of sum_j c_j m_j for bins that one photon reaches at most
    one of, from their means m_j, standard errors se_j (NaN for a bin without events: it
    contributes nothing) and the photon count N. NaN if no bin had an event."""
    c = np.asarray(coef, dtype=np.float64)
    m = np.asarray(mean, dtype=np.float64)
    se = np.asarray(stderr, dtype=np.float64)
    resolved = np.isfinite(se)
    if not resolved.any():
        return float("nan")
    se = np.where(resolved, se, 0.0)
    m = np.where(resolved, m, 0.0)  # an unresolved bin has mass 0
    cm = c * m
    var = np.sum(c * c * se * se) + (np.sum(cm * cm) - np.sum(cm) ** 2) / (photons - 1)
    return float(np.sqrt(max(var, 0.0)))  # (*) is a sum of squares; the clamp only guards rounding
