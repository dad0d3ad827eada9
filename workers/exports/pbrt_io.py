"""The pbrt export's files and their reader: JSON and a little-endian binary, one per (g, eta).

JSON (``*.json``): one object, top-level keys ``g``, ``eta`` and pbrt's ``BSSRDFTable`` field
names, arrays flat and row-major with rho outer (pbrt's ``profile[i * nRadius + j]``)::

    g, eta                  the medium's HG parameter and relative index
    nRhoSamples, nRadiusSamples
    rhoSamples[nRho]        single-scattering albedos
    radiusSamples[nRadius]  optical radii r sigma_t (radiusSamples[0] = 0)
    profile[nRho*nRadius]   2 pi r Sr: density in r of the exitance per unit power entered
    rhoEff[nRho]            Catmull-Rom integral of each profile row, as pbrt computes it
    profileCDF[nRho*nRadius] running integral (unnormalised, last entry of a row = rhoEff)
    profileStderr, rhoEffStderr       standard errors of profile and rhoEff
    profileNodeError        estimated error of each node value from its bin (see nodes.py)
    rhoEffMeasured, rhoEffMeasuredStderr   Rd / (1 - R_spec) over all radii, measured
    rhoBeyondRmax           what rhoEff leaves out of rhoEffMeasured: the fraction leaving
                            beyond the last bin edge (measured) plus the last bin's part
                            outside the last node (estimated); rhoEff + rhoBeyondRmax =
                            rhoEffMeasured
    rhoTruncated, rhoTruncatedStderr  weight still alive at the path cap (max_scatter), per
                            unit power entered: missing from profile and rhoEff (albedo 1
                            needs the cap; 0 with a NaN error where no path reached it)
    profileNegativeMass     integral of the row spline's negative lobes (<= 0): where pbrt's
                            Pdf_Sr clamps to 0 and its sampler never lands (0: the export
                            keeps every row >= 0)
    rangeNegativeMass[nRho-1]  per albedo range [rho_i, rho_i+1]: the most negative negative
                            mass / rhoEff of the rows pbrt interpolates inside it (sampled)
    rangeWorstRho[nRho-1]   the albedo where that was found
    photons[nRho]           photons per albedo
    estimator, units, normalisation, nodeValues   text
    interpolationWarnings   the albedo ranges whose interpolated rows dip by more than
                            NEGLIGIBLE_NEGATIVE of rhoEff (workers/exports/interpolation.py)
    provenance              dataset, version, spec hash, code version, sha256 of the tables

NaN (an unresolved bin's standard error) is written as JSON ``null``.

Binary (``*.bin``), every number little-endian::

    bytes 0..7     magic b"BSSRDFTB"
    uint32         format version (3; version 2 had no range arrays, 1 no rhoTruncated arrays)
    uint32 uint32  nRho, nRadius
    float64 x2     g, eta
    uint32         length L of the metadata JSON (every key above that is not an array)
    L bytes        that JSON, UTF-8, then zero padding to a multiple of 8 bytes
    float64 arrays, in this order: rhoSamples[nRho], radiusSamples[nRadius],
                   profile[nRho*nRadius], rhoEff[nRho], profileCDF[nRho*nRadius],
                   profileStderr[nRho*nRadius], rhoEffStderr[nRho],
                   profileNodeError[nRho*nRadius], rhoEffMeasured[nRho],
                   rhoEffMeasuredStderr[nRho], rhoBeyondRmax[nRho], photons[nRho],
                   profileNegativeMass[nRho], rhoTruncated[nRho], rhoTruncatedStderr[nRho],
                   rangeNegativeMass[nRho-1], rangeWorstRho[nRho-1]

(float64 keeps every value; pbrt's Float is float32, a loader narrows.) :func:`read_pbrt` reads
either file into a :class:`PbrtTable`; :meth:`PbrtTable.bssrdf_table` gives the arrays pbrt
samples (:mod:`workers.models.tabulated`).
"""

from __future__ import annotations

import json
import math
import struct
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from workers.models.tabulated import BSSRDFTable

__all__ = ["PbrtTable", "read_pbrt", "write_pbrt_json", "write_pbrt_binary", "MAGIC", "BINARY_VERSION", "ARRAYS"]

MAGIC = b"BSSRDFTB"
BINARY_VERSION = 3

# (JSON key, attribute, per-rho (0, 1), per-radius (-1), per-node (2) or per albedo range (3)) in the
# binary's array order.
ARRAYS = (
    ("rhoSamples", "rho_samples", 0), ("radiusSamples", "radius_samples", -1), ("profile", "profile", 2),
    ("rhoEff", "rho_eff", 1), ("profileCDF", "profile_cdf", 2), ("profileStderr", "profile_stderr", 2),
    ("rhoEffStderr", "rho_eff_stderr", 1), ("profileNodeError", "profile_node_error", 2),
    ("rhoEffMeasured", "rho_eff_measured", 1), ("rhoEffMeasuredStderr", "rho_eff_measured_stderr", 1),
    ("rhoBeyondRmax", "rho_beyond_rmax", 1), ("photons", "photons", 1),
    ("profileNegativeMass", "profile_negative_mass", 1), ("rhoTruncated", "rho_truncated", 1),
    ("rhoTruncatedStderr", "rho_truncated_stderr", 1), ("rangeNegativeMass", "range_negative_mass", 3),
    ("rangeWorstRho", "range_worst_rho", 3),
)


@dataclass(frozen=True)
class PbrtTable:
    """One (g, eta) table with its errors and provenance; arrays float64, 2-D ones [nRho, nRadius]."""

    g: float
    eta: float
    rho_samples: np.ndarray
    radius_samples: np.ndarray
    profile: np.ndarray
    rho_eff: np.ndarray
    profile_cdf: np.ndarray
    profile_stderr: np.ndarray
    rho_eff_stderr: np.ndarray
    profile_node_error: np.ndarray
    rho_eff_measured: np.ndarray
    rho_eff_measured_stderr: np.ndarray
    rho_beyond_rmax: np.ndarray
    photons: np.ndarray
    profile_negative_mass: np.ndarray
    rho_truncated: np.ndarray
    rho_truncated_stderr: np.ndarray
    range_negative_mass: np.ndarray
    range_worst_rho: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)  # estimator, units, provenance, ...

    def bssrdf_table(self) -> BSSRDFTable:
        """The five arrays pbrt's TabulatedBSSRDF uses."""
        return BSSRDFTable(self.rho_samples, self.radius_samples, self.profile, self.rho_eff, self.profile_cdf)

    def equals(self, other: "PbrtTable") -> bool:
        """Same numbers (NaN equal to NaN) and metadata."""
        same = [np.array_equal(getattr(self, f.name), getattr(other, f.name), equal_nan=True)
                for f in fields(self) if isinstance(getattr(self, f.name), np.ndarray)]
        return all(same) and (self.g, self.eta, self.meta) == (other.g, other.eta, other.meta)


def _json_number(x: float) -> float | None:
    return None if not math.isfinite(x) else float(x)


def write_pbrt_json(table: PbrtTable, path: str | Path) -> None:
    """The JSON file of the module docstring (floats written to round-trip exactly)."""
    doc: dict[str, Any] = {"g": table.g, "eta": table.eta, "nRhoSamples": len(table.rho_samples),
                           "nRadiusSamples": len(table.radius_samples)}
    for key, attr, _kind in ARRAYS:
        doc[key] = [_json_number(x) for x in np.asarray(getattr(table, attr), dtype=np.float64).ravel()]
    doc.update(table.meta)
    Path(path).write_text(json.dumps(doc, indent=1, sort_keys=False, allow_nan=False) + "\n", encoding="utf-8")


def write_pbrt_binary(table: PbrtTable, path: str | Path) -> None:
    """The binary file of the module docstring."""
    meta = json.dumps({"g": table.g, "eta": table.eta, **table.meta}, sort_keys=True, allow_nan=False).encode("utf-8")
    head = MAGIC + struct.pack("<III", BINARY_VERSION, len(table.rho_samples), len(table.radius_samples))
    head += struct.pack("<dd", table.g, table.eta) + struct.pack("<I", len(meta)) + meta
    head += b"\0" * (-len(head) % 8)
    body = b"".join(np.asarray(getattr(table, attr), dtype="<f8").ravel().tobytes() for _k, attr, _kind in ARRAYS)
    Path(path).write_bytes(head + body)


def _read_json(path: Path) -> PbrtTable:
    doc = json.loads(path.read_text(encoding="utf-8"))
    n_rho, n_r = doc.pop("nRhoSamples"), doc.pop("nRadiusSamples")
    shapes = {0: (n_rho,), -1: (n_r,), 1: (n_rho,), 2: (n_rho, n_r), 3: (n_rho - 1,)}
    arrays = {attr: np.array([np.nan if x is None else x for x in doc.pop(key)], dtype=np.float64).reshape(shapes[kind])
              for key, attr, kind in ARRAYS}
    return PbrtTable(g=doc.pop("g"), eta=doc.pop("eta"), meta=doc, **arrays)


def _read_binary(path: Path) -> PbrtTable:
    data = path.read_bytes()
    if data[:8] != MAGIC:
        raise ValueError(f"{path} is not a pbrt table export (magic {data[:8]!r}, expected {MAGIC!r})")
    version, n_rho, n_r = struct.unpack_from("<III", data, 8)
    if version != BINARY_VERSION:
        raise ValueError(f"{path}: binary format version {version}, this reader knows {BINARY_VERSION}")
    g, eta = struct.unpack_from("<dd", data, 20)
    (length,) = struct.unpack_from("<I", data, 36)
    meta = json.loads(data[40:40 + length].decode("utf-8"))
    offset = 40 + length + (-(40 + length) % 8)
    shapes = {0: (n_rho,), -1: (n_r,), 1: (n_rho,), 2: (n_rho, n_r), 3: (n_rho - 1,)}
    arrays = {}
    for _key, attr, kind in ARRAYS:
        count = math.prod(shapes[kind])
        arrays[attr] = np.frombuffer(data, dtype="<f8", count=count, offset=offset).astype(np.float64).reshape(shapes[kind])
        offset += 8 * count
    if offset != len(data):
        raise ValueError(f"{path}: {len(data) - offset} bytes after the last array; the file is damaged")
    meta.pop("g"), meta.pop("eta")
    return PbrtTable(g=g, eta=eta, meta=meta, **arrays)


def read_pbrt(path: str | Path) -> PbrtTable:
    """Read a pbrt export file (``.json`` or ``.bin``) into a :class:`PbrtTable`."""
    path = Path(path)
    return _read_binary(path) if path.suffix == ".bin" else _read_json(path)
