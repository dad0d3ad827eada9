"""Arrow schemas of the stored tables, their column docs and the Parquet metadata keys.

Three tables per dataset version (docs/architecture.md, "Physics conventions" and "Datasets and exports"); every
row is for one (estimator, medium, incidence angle, channel, component), and carries the
medium's coordinates ``medium`` (its index in the job: 0 for a single medium, see
:mod:`schema.media`), ``albedo``, ``g`` and ``eta`` (of the row's channel), so the media of a
sweep are rows of one table:

* ``RADIAL_SCHEMA`` -- the radial profile Rd(r) = sum of G over an annulus / its area [1/mm^2];
* ``BINS_SCHEMA`` -- G (flux fraction) and S (the BSSRDF averaged over the bin in dA d omega,
  [1/(mm^2 sr)]) per spatial x directional bin;
* ``SUMMARY_SCHEMA`` -- totals: specular reflectance, diffuse reflectance, absorbed and truncated
  weight, photon count.

All tallies are normalised by the incident power 1; standard errors come from the batches.
Strings: ``estimator`` in {"hybrid", "exits", "connections"}, ``component`` in {"single", "multiple",
"total"}, ``channel`` a channel name of the medium. Version rule: adding a column or a metadata
key keeps ``SCHEMA_VERSION``; renaming, removing or changing the meaning or unit of a column bumps
it.
"""

from __future__ import annotations

import json
from typing import Any

import pyarrow as pa

__all__ = [
    "SCHEMA_VERSION",
    "META_SPEC",
    "META_RUN",
    "META_SCHEMA_VERSION",
    "ESTIMATORS",
    "COMPONENTS",
    "COLUMN_DOCS",
    "RADIAL_SCHEMA",
    "BINS_SCHEMA",
    "SUMMARY_SCHEMA",
    "TABLE_SCHEMAS",
    "table_metadata",
]

SCHEMA_VERSION = "2"
"""Version of the stored-table layout (see the version rule in the module docstring).  2: the
theta_s and phi_o bins are centred on the plane of incidence (their edge columns start at -h/2)
and S_stderr is NaN where S_infinite_variance is 1."""

META_SPEC = b"bssrdf.spec"
"""Parquet/Arrow metadata key: the spec's canonical JSON (``SimulationSpec.canonical_json``)."""
META_RUN = b"bssrdf.run"
"""Metadata key: JSON of run facts (code version, seeds, photon counts, timings, checksums)."""
META_SCHEMA_VERSION = b"bssrdf.schema_version"
"""Metadata key: ``SCHEMA_VERSION`` as ASCII."""

ESTIMATORS = ("hybrid", "exits", "connections")
"""Values of the ``estimator`` column (a spec's ``"both"`` gives rows of each)."""
COMPONENTS = ("single", "multiple", "total")
"""Values of the ``component`` column: exactly one scattering event, two or more, all."""

COLUMN_DOCS: dict[str, str] = {
    "estimator": 'Estimator that produced the row: "hybrid" (the default), "exits" or "connections".',
    "medium": "Index of the medium in the job (0 for a single medium; a sweep's media are "
              "numbered albedo fastest, eta slowest: see schema.media).",
    "albedo": "Single-scattering albedo sigma_s / sigma_t of the row's medium and channel.",
    "g": "Henyey-Greenstein mean cosine of the row's medium and channel.",
    "eta": "Relative index of refraction of the row's medium.",
    "incidence_deg": "Incidence angle theta_i [deg] in the x-z plane, 0 = normal.",
    "channel": "Spectral channel name of the medium (e.g. R, G, B or c0).",
    "component": 'Scattering order: "single" (one event), "multiple" (two or more), "total".',
    "r_lo_mm": "Inner radius of the bin [mm] (inclusive).",
    "r_hi_mm": "Outer radius of the bin [mm] (exclusive).",
    "Rd_r": "Radial diffuse reflectance Rd(r): flux through the annulus / its area [1/mm^2].",
    "Rd_r_stderr": "Standard error of Rd_r [1/mm^2]; NaN where no event contributed (no error bar).",
    "events": "Contributing events of the row's estimate: exits tallied, connection samples with a "
              "nonzero value (int64). 0 means unresolved: the estimate is 0 with a NaN standard error.",
    "unresolved_bins": "Bins of the bins table (inside r_max) with no contributing event for this "
                       "estimator, configuration and component (int64).",
    "theta_s_lo": "Lower exit azimuth theta_s [rad] from +x (inclusive); bins are centred on +x, "
                  "bin k = [(k - 1/2) h, (k + 1/2) h), h = 2 pi / n, so lo runs from -h/2; an angle "
                  "is taken modulo 2 pi into [-h/2, 2 pi - h/2).",
    "theta_s_hi": "Upper exit azimuth theta_s [rad] (exclusive).",
    "cos_theta_o_lo": "Lower cos(theta_o) of the outgoing direction (inclusive), in [0, 1].",
    "cos_theta_o_hi": "Upper cos(theta_o) (exclusive).",
    "phi_o_lo": "Lower outgoing azimuth phi_o [rad] from the outward radial direction (inclusive); "
                "bins are centred on it, bin k = [(k - 1/2) h, (k + 1/2) h), h = 2 pi / n, so lo "
                "runs from -h/2 and bin 0 holds phi_o = 0 (mirror of bin k: bin (n - k) mod n).",
    "phi_o_hi": "Upper outgoing azimuth phi_o [rad] (exclusive).",
    "G": "Fraction of the incident power leaving through the bin [dimensionless].",
    "G_stderr": "Standard error of G [dimensionless]; NaN where no event contributed.",
    "S": "BSSRDF averaged over the bin in dA d omega: sum w / cos(theta_o) / (A Omega) "
         "[1/(mm^2 sr)]; includes the entry Fresnel factor.",
    "S_stderr": "Standard error of S [1/(mm^2 sr)]; NaN where no event contributed and where "
                "S_infinite_variance is 1.",
    "S_infinite_variance": "1 where the estimator's per-photon contribution to S has an infinite "
                           "second moment, else 0 (int64): the exit tally's w / cos(theta_o) in the "
                           "lowest cos(theta_o) bin at eta = 1 (exits: every component; hybrid: "
                           "multiple and total). S is unbiased there, but no standard error is "
                           "valid (one run's error is skewed low), so S_stderr is NaN.",
    "R_spec": "Specular reflectance at entry, Fr(cos theta_i, eta) [dimensionless].",
    "Rd": "Total diffuse reflectance: sum of G over all bins [dimensionless].",
    "Rd_stderr": "Standard error of Rd [dimensionless]; NaN where no event contributed.",
    "Rd_beyond_rmax": "Diffuse reflectance leaving beyond the outer radial edge [dimensionless].",
    "Rd_beyond_rmax_stderr": "Standard error of Rd_beyond_rmax [dimensionless].",
    "absorbed": "Fraction of the incident power absorbed in the medium [dimensionless].",
    "absorbed_stderr": "Standard error of absorbed [dimensionless].",
    "truncated": "Weight still alive when the path hit max_scatter [dimensionless].",
    "truncated_stderr": "Standard error of truncated [dimensionless].",
    "photons": "Photons simulated for this incidence angle and channel.",
}
"""Column name -> meaning and unit. Also stored as each field's ``doc`` metadata."""

_STRING = ("estimator", "channel", "component")
_INT64 = ("photons", "medium", "events", "unresolved_bins", "S_infinite_variance")


def _schema(names: list[str]) -> pa.Schema:
    def typ(n: str) -> pa.DataType:
        return pa.string() if n in _STRING else pa.int64() if n in _INT64 else pa.float64()

    return pa.schema(
        [pa.field(n, typ(n), nullable=False, metadata={b"doc": COLUMN_DOCS[n].encode()})
         for n in names]
    )


_KEYS = ["estimator", "medium", "albedo", "g", "eta", "incidence_deg", "channel", "component"]

RADIAL_SCHEMA = _schema(_KEYS + ["r_lo_mm", "r_hi_mm", "Rd_r", "Rd_r_stderr", "events"])
"""One row per radial bin."""

BINS_SCHEMA = _schema(_KEYS + [
    "r_lo_mm", "r_hi_mm", "theta_s_lo", "theta_s_hi", "cos_theta_o_lo", "cos_theta_o_hi",
    "phi_o_lo", "phi_o_hi", "G", "G_stderr", "S", "S_stderr", "S_infinite_variance", "events",
])
"""One row per spatial x directional bin."""

SUMMARY_SCHEMA = _schema(_KEYS + [
    "R_spec", "Rd", "Rd_stderr", "Rd_beyond_rmax", "Rd_beyond_rmax_stderr", "absorbed",
    "absorbed_stderr", "truncated", "truncated_stderr", "photons", "unresolved_bins",
])
"""One row per (estimator, incidence angle, channel, component)."""

TABLE_SCHEMAS: dict[str, pa.Schema] = {
    "radial": RADIAL_SCHEMA, "bins": BINS_SCHEMA, "summary": SUMMARY_SCHEMA,
}
"""Table name -> schema."""


def table_metadata(spec_json: str, run: dict[str, Any] | None = None) -> dict[bytes, bytes]:
    """Schema-level metadata for a stored table: the spec's canonical JSON, run facts as
    sorted-key JSON, and the schema version. Use ``schema.with_metadata(table_metadata(...))``."""
    return {
        META_SPEC: spec_json.encode("utf-8"),
        META_RUN: json.dumps(run or {}, sort_keys=True, separators=(",", ":")).encode("utf-8"),
        META_SCHEMA_VERSION: SCHEMA_VERSION.encode("ascii"),
    }
