"""The version page's figures: the SVGs of the version's stored ``plots`` export.

The page shows the same figures as ``bssrdf export NAME --format plots``, taken from that export
(:func:`service.datasets.exports.ensure_export`): made once from the version's verified tables on
the first request, stored beside the version with its sha256, then served from the stored
archive, each SVG checked against the sha256 its manifest records. Unpacked archives are kept in
memory (:data:`CACHE_ARCHIVES` of them, keyed by their sha256), so a page's images cost one read.

    figures = plot_figures(store, storage, record)        # [Figure(...)], or raises MissingDependency
    data = svg_bytes(store, storage, record, "rd-exits-g+0.5000-eta1.3000-inc0.svg")
"""

from __future__ import annotations

import hashlib
import io
import threading
import zipfile
from collections import OrderedDict
from dataclasses import dataclass

from service.datasets import DatasetStorage
from service.datasets.exports import ensure_export, read_export
from service.store import ChecksumMismatch, DatasetVersionRecord, ExportRecord, JobStore

__all__ = ["Figure", "plot_figures", "svg_bytes", "CACHE_ARCHIVES", "KINDS"]

CACHE_ARCHIVES = 8
"""Unpacked plots archives kept in memory."""
KINDS = {"rd": "Rd(r)", "s": "S over the outgoing hemisphere", "albedo-map": "Albedo map", "other": "Other figures"}
"""Figure kinds by file-name prefix, in the order the page shows them."""

_cache: OrderedDict[str, dict[str, bytes]] = OrderedDict()
_lock = threading.Lock()


@dataclass(frozen=True)
class Figure:
    """One SVG of the plots export: its file name, kind (a :data:`KINDS` key), caption and sha256."""

    filename: str
    kind: str
    caption: str
    sha256: str


def _kind(stem: str) -> str:
    return next((k for k in ("albedo-map", "rd", "s") if stem.startswith(k + "-")), "other")


def _caption(stem: str, kind: str) -> str:
    """``rd-exits-g+0.5000-eta1.3000-inc0`` -> "exits, g = 0.5, eta = 1.3, theta_i = 0 deg"."""
    if kind == "other":
        return stem
    parts = stem[len(kind) + 1:].split("-g")
    estimator, rest = parts[0], "-g".join(parts[1:])
    text = [estimator]
    for piece in rest.replace("-eta", " eta").replace("-inc", " inc").split():
        if piece.startswith(("+", "-")) or piece[:1].isdigit():
            text.append(f"g = {float(piece):g}")
        elif piece.startswith("eta"):
            text.append(f"eta = {float(piece[3:]):g}")
        elif piece.startswith("inc"):
            text.append(f"theta_i = {float(piece[3:]):g} deg")
    return ", ".join(text)


def _plots(store: JobStore, storage: DatasetStorage, record: DatasetVersionRecord) -> ExportRecord:
    return ensure_export(store, storage, record.name, record.version, "plots")[1]


def plot_figures(store: JobStore, storage: DatasetStorage, record: DatasetVersionRecord) -> list[Figure]:
    """The SVG figures of the version's plots export (made now if it does not exist yet), by
    kind (Rd, S, albedo map) then name. Raises MissingDependency without matplotlib."""
    export = _plots(store, storage, record)
    figures = []
    for name, info in export.meta.get("files", {}).items():
        if name.endswith(".svg"):
            stem = name[:-4]
            kind = _kind(stem)
            figures.append(Figure(name, kind, _caption(stem, kind), info["sha256"]))
    order = list(KINDS)
    return sorted(figures, key=lambda f: (order.index(f.kind), f.filename))


def _unpacked(storage: DatasetStorage, record: DatasetVersionRecord, export: ExportRecord) -> dict[str, bytes]:
    with _lock:
        if export.sha256 in _cache:
            _cache.move_to_end(export.sha256)
            return _cache[export.sha256]
    archive = read_export(storage, record, export)  # the archive's sha256 checked
    with zipfile.ZipFile(io.BytesIO(archive)) as zf:
        files = {n: zf.read(n) for n in zf.namelist() if n.endswith(".svg")}
    with _lock:
        _cache[export.sha256] = files
        while len(_cache) > CACHE_ARCHIVES:
            _cache.popitem(last=False)
    return files


def svg_bytes(store: JobStore, storage: DatasetStorage, record: DatasetVersionRecord, filename: str) -> bytes | None:
    """The bytes of SVG ``filename`` of the version's plots export, checked against the sha256
    its manifest records (ChecksumMismatch otherwise); None if the export has no such SVG."""
    export = _plots(store, storage, record)
    info = export.meta.get("files", {}).get(filename)
    if info is None or not filename.endswith(".svg"):
        return None
    data = _unpacked(storage, record, export).get(filename)
    if data is None or hashlib.sha256(data).hexdigest() != info["sha256"]:
        raise ChecksumMismatch(f"{record.name} v{record.version}: plots export file {filename} differs from the "
                               "sha256 its manifest records: the stored export is damaged")
    return data
