"""The stored tables as arrays: radial profiles and summary rows keyed by their key columns.

A key is (estimator, medium, incidence_deg, channel, component); every row also carries its
medium's coordinates albedo, g, eta (schema.tables). The rows of one key are contiguous in the
stored order (workers.fold.output), which this module relies on and checks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyarrow as pa

from .source import ExportError, table_arrays

__all__ = ["Key", "RadialProfile", "radial_profiles", "summary_rows", "KEY_COLUMNS"]

KEY_COLUMNS = ("estimator", "medium", "incidence_deg", "channel", "component")

Key = tuple[str, int, float, str, str]
"""(estimator, medium, incidence_deg, channel, component)."""


@dataclass(frozen=True)
class RadialProfile:
    """Rd(r) of one key: bins [r_lo, r_hi) [mm], Rd_r and its standard error [1/mm^2] (NaN
    where a bin had no event), with the medium coordinates of the rows."""

    key: Key
    albedo: float
    g: float
    eta: float
    r_lo_mm: np.ndarray
    r_hi_mm: np.ndarray
    rd: np.ndarray
    rd_stderr: np.ndarray

    @property
    def masses(self) -> tuple[np.ndarray, np.ndarray]:
        """(G, se): the fraction of incident power through each annulus, Rd_r pi (r_hi^2 - r_lo^2)."""
        area = np.pi * (self.r_hi_mm**2 - self.r_lo_mm**2)
        return self.rd * area, self.rd_stderr * area


def _keys(cols: dict[str, np.ndarray]) -> list[Key]:
    return list(zip(cols["estimator"], (int(m) for m in cols["medium"]), (float(i) for i in cols["incidence_deg"]),
                    cols["channel"], cols["component"]))


def radial_profiles(radial: pa.Table) -> dict[Key, RadialProfile]:
    """Every radial profile of the table, by key, in stored order."""
    cols = table_arrays(radial)
    keys = _keys(cols)
    out: dict[Key, RadialProfile] = {}
    start = 0
    for i in range(1, len(keys) + 1):
        if i < len(keys) and keys[i] == keys[start]:
            continue
        key = keys[start]
        if key in out:
            raise ExportError(f"radial rows of {key} are not contiguous: the table was not written by workers.fold.output")
        sl = slice(start, i)
        out[key] = RadialProfile(key, float(cols["albedo"][start]), float(cols["g"][start]), float(cols["eta"][start]),
                                 cols["r_lo_mm"][sl].astype(np.float64), cols["r_hi_mm"][sl].astype(np.float64),
                                 cols["Rd_r"][sl].astype(np.float64), cols["Rd_r_stderr"][sl].astype(np.float64))
        start = i
    return out


def summary_rows(summary: pa.Table) -> dict[Key, dict]:
    """Every summary row as a dict, by key."""
    rows = summary.to_pylist()
    return {(r["estimator"], int(r["medium"]), float(r["incidence_deg"]), r["channel"], r["component"]): r
            for r in rows}
