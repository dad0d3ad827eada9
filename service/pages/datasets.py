"""The datasets pages: datasets, a dataset's versions, a version with its figures and downloads.

    GET /datasets                                          every dataset with its latest version
    GET /datasets/{name}                                   its versions (tombstones included)
    GET /datasets/{name}/versions/{version}                spec, provenance, summary, figures, links
    GET /datasets/{name}/versions/{version}/plots/{file}   one SVG of the version's plots export
    GET /datasets/{name}/versions/{version}/files/{file}   a table, as the API serves it
    GET /datasets/{name}/versions/{version}/exports/{fmt}  an export archive, as the API serves it

``version`` is a number or ``latest``. The downloads go through the API's own code path
(:func:`service.api.downloads.file_response`: sha256 checked, ETag, Range), under the pages'
sign-in (a browser with a session cookie can follow them where reads need a token).
"""

from __future__ import annotations

import json
from typing import Any

from fastapi import APIRouter, Request
from fastapi.responses import Response

from schema.names import InvalidName, check_name
from service.api.downloads import file_response
from service.datasets import DatasetStorage, expected_files, verified_path
from service.datasets.exports import ensure_export
from service.api.deps import SettingsDep, StorageDep, StoreDep
from service.pages.auth import PageError
from service.pages.jobs import require_read
from service.pages.plots import KINDS, plot_figures, svg_bytes
from service.pages.render import page
from service.store import DatasetVersionRecord, JobStore, VersionDeleted, VersionNotFound
from workers.exports import FORMATS, ExportError, MissingDependency, UnknownFormat

__all__ = ["router", "summary_rows", "SUMMARY_ROWS"]

router = APIRouter(include_in_schema=False)

SUMMARY_ROWS = 200
"""Rows of the summary table shown on the page (the rest are in summary.json / summary.parquet)."""
EXPORT_NOTES = {
    "pbrt": "pbrt's tabulated profile per (g, eta), JSON and binary",
    "albedo-map": "albedo -> total diffuse reflectance, with the dipole's and Christensen-Burley's relations",
    "exr": "OpenEXR images of S and its standard error",
    "npz": "every table as arrays with named axes",
    "csv": "every table as CSV with units",
    "plots": "the figures on this page, as PNG and SVG",
}
SVG_HEADERS = {"Content-Security-Policy": "default-src 'none'; style-src 'unsafe-inline'; img-src data:",
               "X-Content-Type-Options": "nosniff", "Cache-Control": "public, max-age=31536000, immutable"}


def _name(name: str) -> str:
    try:
        return check_name(name, "dataset name")
    except InvalidName as exc:
        raise PageError(404, f"no such dataset: {exc}") from None


def _version(store: JobStore, name: str, version: str) -> DatasetVersionRecord:
    """The version named in the path (404 / 410 as pages)."""
    _name(name)
    if version == "latest":
        number = None
    elif version.isascii() and version.isdigit() and len(version) <= 10 and 1 <= int(version) <= 2**31 - 1:
        number = int(version)
    else:
        raise PageError(404, f"version must be a number or 'latest'; received {version[:40]!r}")
    try:
        return store.get_version(name, number)
    except VersionDeleted as exc:
        raise PageError(410, f"{exc}") from None
    except VersionNotFound:
        which = "no versions" if number is None else f"no version {number}"
        raise PageError(404, f"dataset {name!r} has {which}; datasets are listed on /datasets") from None


def summary_rows(doc: dict[str, Any]) -> list[dict[str, Any]]:
    """summary.json's results as table rows: one per (medium, estimator, incidence, channel),
    with R_spec and the single / multiple / total Rd with their standard errors."""
    rows: dict[tuple, dict[str, Any]] = {}
    for r in doc.get("results", []):
        key = (r.get("medium", 0), r["estimator"], r["incidence_deg"], r["channel"])
        row = rows.setdefault(key, {"medium": key[0], "estimator": key[1], "incidence_deg": key[2], "channel": key[3],
                                    "albedo": r.get("albedo"), "g": r.get("g"), "eta": r.get("eta"),
                                    "R_spec": r.get("R_spec"), "photons": r.get("photons")})
        row[r["component"]] = (r.get("Rd"), r.get("Rd_stderr"))
        if r["component"] == "total":
            row["unresolved_bins"] = r.get("unresolved_bins")
    return list(rows.values())


def _summary(storage: DatasetStorage, record: DatasetVersionRecord) -> dict[str, Any]:
    files = expected_files(record)
    path = verified_path(storage, record, "summary.json", files["summary.json"])  # ChecksumMismatch -> 500
    with storage.fs.open_input_stream(path) as f:
        return json.loads(f.read())


@router.get("/datasets")
def datasets_page(request: Request, settings: SettingsDep, store: StoreDep) -> Response:
    require_read(request, settings)
    return page(request, settings, "datasets.html", datasets=store.list_datasets())


@router.get("/datasets/{name}")
def dataset_page(request: Request, name: str, settings: SettingsDep, store: StoreDep) -> Response:
    require_read(request, settings)
    versions = store.list_versions(_name(name), deleted=True)
    if not versions:
        raise PageError(404, f"no dataset named {name!r}; datasets are listed on /datasets")
    return page(request, settings, "dataset.html", name=name, versions=versions)


@router.get("/datasets/{name}/versions/{version}")
def version_page(request: Request, name: str, version: str, settings: SettingsDep, store: StoreDep,
                 storage: StorageDep) -> Response:
    require_read(request, settings)
    record = _version(store, name, version)
    summary = _summary(storage, record)
    try:
        figures, plots_problem = plot_figures(store, storage, record), None
    except MissingDependency as exc:
        figures, plots_problem = [], f"{exc} on this server"
    except ExportError as exc:
        figures, plots_problem = [], f"no figures: {exc}"
    made = {e.format: e for e in store.list_exports(record.name, record.version)}
    spec = record.meta.get("spec", {})
    rows = summary_rows(summary)
    per_config = summary.get("run", {}).get("photons_per_config")  # a list per medium for a sweep
    per_config = per_config[0] if isinstance(per_config, list) and per_config else per_config
    return page(request, settings, "version.html", v=record, meta=record.meta, spec=spec,
                description=spec.get("description"), run=summary.get("run", {}), files=expected_files(record),
                sizes={k: f.get("bytes") for k, f in record.meta.get("files", {}).items()},
                rows=rows[:SUMMARY_ROWS], more_rows=max(0, len(rows) - SUMMARY_ROWS),
                sweep=spec.get("sweep") is not None, per_config=per_config, figures=figures, kinds=KINDS, plots_problem=plots_problem,
                formats=[(f, EXPORT_NOTES.get(f, ""), made.get(f)) for f in FORMATS],
                base=f"/datasets/{record.name}/versions/{record.version}")


@router.get("/datasets/{name}/versions/{version}/plots/{filename}")
def plot_svg(request: Request, name: str, version: str, filename: str, settings: SettingsDep, store: StoreDep,
             storage: StorageDep) -> Response:
    require_read(request, settings)
    record = _version(store, name, version)
    try:
        data = svg_bytes(store, storage, record, filename)
    except MissingDependency as exc:
        raise PageError(501, f"{exc} on this server") from None
    if data is None:
        raise PageError(404, f"{record.name} v{record.version} has no figure {filename[:80]!r}")
    return Response(data, media_type="image/svg+xml", headers=SVG_HEADERS)


@router.api_route("/datasets/{name}/versions/{version}/files/{filename}", methods=["GET", "HEAD"])
def download_file(request: Request, name: str, version: str, filename: str, settings: SettingsDep,
                  store: StoreDep, storage: StorageDep) -> Response:
    require_read(request, settings)
    record = _version(store, name, version)
    expected = expected_files(record)
    if filename not in expected:  # only catalogued names: no path ever comes from the request
        raise PageError(404, f"{record.name} v{record.version} has no file {filename[:80]!r}; "
                                 f"available: {', '.join(sorted(expected))}")
    return file_response(request, storage, record, filename, expected[filename],
                         download_name=f"{record.name}-v{record.version}-{filename}")


@router.api_route("/datasets/{name}/versions/{version}/exports/{fmt}", methods=["GET", "HEAD"])
def download_export(request: Request, name: str, version: str, fmt: str, settings: SettingsDep,
                    store: StoreDep, storage: StorageDep) -> Response:
    require_read(request, settings)
    record = _version(store, name, version)
    try:
        record, export = ensure_export(store, storage, record.name, record.version, fmt)
    except UnknownFormat as exc:
        raise PageError(404, str(exc)) from None
    except MissingDependency as exc:
        raise PageError(501, f"{exc} on this server") from None
    except ExportError as exc:
        raise PageError(422, f"{record.name} v{record.version} cannot be exported as {fmt}: {exc}") from None
    return file_response(request, storage, record, export.filename, export.sha256,
                         download_name=f"{record.name}-v{record.version}-{fmt}.zip")
