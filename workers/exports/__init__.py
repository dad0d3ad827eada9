"""Exports of a dataset version for renderers and people (torch-free).

    source = ExportSource.from_directory("out")            # or built from a stored version
    names = write_export("pbrt", source, "out/pbrt")       # the files written

Formats (:data:`FORMATS`): ``pbrt`` (pbrt's tabulated profile per (g, eta), JSON and binary,
:mod:`.pbrt`), ``albedo-map`` (albedo -> total diffuse reflectance with the dipole's and
Christensen-Burley's relations, :mod:`.albedo_map`), ``exr`` (OpenEXR images of S,
:mod:`.exr`), ``npz`` and ``csv`` (arrays and tables with named axes and units, :mod:`.arrays`)
and ``plots`` (matplotlib PNG and SVG, :mod:`.plots`; needs the ``plot`` extra). Every export
also gets ``export.json``: its provenance and the sha256 of each file it wrote.
"""

from __future__ import annotations

import hashlib
import importlib
import json
from pathlib import Path

from .source import ExportError, ExportSource

__all__ = ["FORMATS", "write_export", "check_format", "ExportError", "ExportSource", "MissingDependency",
           "UnknownFormat", "MANIFEST"]

FORMATS: dict[str, str] = {
    "pbrt": "workers.exports.pbrt:write_pbrt",
    "albedo-map": "workers.exports.albedo_map:write_albedo_map",
    "exr": "workers.exports.exr:write_exr",
    "npz": "workers.exports.arrays:write_npz",
    "csv": "workers.exports.arrays:write_csv",
    "plots": "workers.exports.plots:write_plots",
}
"""Format name -> its writer ``module:function(source, out_dir) -> file names``; resolved on use,
so a format's optional dependency (matplotlib for plots) is only needed when it is made."""

MANIFEST = "export.json"
"""The file every export writes last: provenance plus ``{"files": {name: {"sha256", "bytes"}}}``."""


class MissingDependency(ExportError):
    """A format needs a package that is not installed (the message names the extra)."""


class UnknownFormat(ExportError):
    """The format is not one of :data:`FORMATS` (the message lists them)."""


def check_format(fmt: str) -> None:
    """UnknownFormat unless ``fmt`` names a format of :data:`FORMATS` (the one check every
    caller uses: the CLI, the API, the pages and the dataset store)."""
    if fmt not in FORMATS:
        received = fmt if len(fmt) <= 40 else fmt[:40] + "..."
        raise UnknownFormat(f"unknown export format {received!r}: must be one of {', '.join(FORMATS)}")


def _writer(fmt: str):
    check_format(fmt)
    module, func = FORMATS[fmt].split(":")
    try:
        return getattr(importlib.import_module(module), func)
    except ModuleNotFoundError as exc:
        if exc.name and exc.name.split(".")[0] in ("matplotlib",):
            raise MissingDependency(f"the {fmt} export needs {exc.name}: pip install 'bssrdf-db[plot]'") from exc
        raise


def write_export(fmt: str, source: ExportSource, out_dir: str | Path) -> list[str]:
    """Write export ``fmt`` of ``source`` into the (existing, empty) directory ``out_dir``,
    then its manifest; returns every file name, the manifest last."""
    out = Path(out_dir)
    names = sorted(_writer(fmt)(source, out))
    files = {n: {"sha256": hashlib.sha256((out / n).read_bytes()).hexdigest(), "bytes": (out / n).stat().st_size}
             for n in names}
    manifest = dict(source.provenance(fmt), files=files)
    (out / MANIFEST).write_text(json.dumps(manifest, indent=2, sort_keys=True) + "\n", encoding="utf-8")
    return names + [MANIFEST]
