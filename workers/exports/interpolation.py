"""Where pbrt's interpolation between albedo rows makes a profile it cannot sample.

pbrt evaluates and samples a tabulated BSSRDF at any albedo rho between the rows by combining the
rows with Catmull-Rom weights in rho (workers.models.tabulated ``BSSRDFTable.row``): inside [rho_i,
rho_i+1] the outer rows rho_i-1 and rho_i+2 get weights <= 0. Every exported row is >= 0
(workers.exports.conserving), but the combination is not where a row with a negative weight has
much more tail than the rows it is mixed with: at albedo 0.85 between rows 0.5 and 0.9 with a row
0.99 next, the 0.99 row's long tail, taken with a negative weight, pulls the interpolated profile
below 0 beyond a few mean free paths. There pbrt's Pdf_Sr clamps to 0, the interpolated CDF
falls where the row is negative (and may rise above its final value), and Sample_Sr, inverting
that CDF by binary search, puts radii where Pdf_Sr does not: sampling and evaluation disagree by
up to about the negative mass.

The export reports, per albedo range [rho_i, rho_i+1], the most negative ratio

    (integral of min(P(rho, r), 0) dr) / rhoEff(rho)     (<= 0; 0: the CDF is monotone)

over RANGE_SAMPLES albedos evenly inside the range (the rows themselves are >= 0), with the
albedo where it was found. Ranges beyond NEGLIGIBLE_NEGATIVE are listed in the metadata: a
denser albedo axis there (more rows, e.g. pbrt's own 100 rows dense near 1) removes them.
"""

from __future__ import annotations

import numpy as np

from workers.models.catmull_rom import negative_mass
from workers.models.tabulated import BSSRDFTable

__all__ = ["range_negative_mass", "interpolated_fraction", "interpolation_warnings", "RANGE_SAMPLES", "NEGLIGIBLE_NEGATIVE"]

RANGE_SAMPLES = 15
"""Albedos examined inside each range (evenly spaced, ends excluded)."""
NEGLIGIBLE_NEGATIVE = 1e-4
"""Negative mass per unit rhoEff below which a range is not listed: a sampler missing 1e-4 of the
profile is invisible at the photon counts tables are measured with (1e-4 is below rhoEff's
standard error up to ~1e8 photons)."""


def interpolated_fraction(table: BSSRDFTable, rho: float) -> float:
    """Negative mass / rhoEff of the row pbrt interpolates at ``rho`` (0 where rhoEff <= 0)."""
    row = table.row(rho)
    eff = table.row(rho, table.rho_eff[:, None])
    if row is None or eff is None or not eff[0] > 0:
        return 0.0
    return float(negative_mass(table.radius_samples, row) / eff[0])


def range_negative_mass(table: BSSRDFTable, samples: int = RANGE_SAMPLES) -> tuple[np.ndarray, np.ndarray]:
    """(worst[nRho-1], at[nRho-1]): per albedo range the most negative interpolated fraction of
    :func:`interpolated_fraction` at ``samples`` albedos inside it, and the albedo (NaN if 0)."""
    rho = table.rho_samples
    worst = np.zeros(len(rho) - 1)
    at = np.full(len(rho) - 1, np.nan)
    steps = np.arange(1, samples + 1) / (samples + 1)
    for i in range(len(rho) - 1):
        for a in rho[i] + steps * (rho[i + 1] - rho[i]):
            f = interpolated_fraction(table, float(a))
            if f < worst[i]:
                worst[i], at[i] = f, a
    return worst, at


def interpolation_warnings(rho, worst, at) -> list[dict]:
    """The ranges whose interpolated rows dip by more than NEGLIGIBLE_NEGATIVE, for the metadata."""
    return [{"rhoRange": [float(rho[i]), float(rho[i + 1])], "negativeMassFraction": float(worst[i]),
             "atRho": float(at[i]),
             "meaning": "pbrt's interpolated profile dips below 0 here: Pdf_Sr clamps, the CDF is not monotone and "
                        "Sample_Sr misplaces up to about this fraction of the profile; add albedo rows in this range"}
            for i in range(len(worst)) if worst[i] < -NEGLIGIBLE_NEGATIVE]
