"""``/v1/datasets``: published dataset versions, their metadata, summaries, files and exports."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, HTTPException, Path, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import Response, StreamingResponse
from pydantic import AfterValidator
from pydantic_core import PydanticCustomError

from schema.names import NAME_MAX, NAME_PATTERN, NAME_RULE, InvalidName, check_name

from service.api.deps import AuthDep, ReadAuthDep, StorageDep, StoreDep, token_fingerprint
from service.api.downloads import DOWNLOAD_RESPONSES, file_response
from service.api.errors import error_responses, shorten
from service.api.models import DatasetPublic, DatasetVersionDetail, DatasetVersionPublic, dataset_from_record
from service.datasets import expected_files
from service.datasets.exports import ensure_export
from service.store import DatasetVersionRecord, JobStore, VersionDeleted, VersionNotFound
from workers.exports import FORMATS, ExportError, MissingDependency, UnknownFormat

__all__ = ["router", "parse_version", "NamePath", "VersionPath", "VERSION_MAX"]

router = APIRouter(prefix="/v1/datasets", tags=["datasets"])


VERSION_MAX = 2**31 - 1
"""Largest version number (the catalog's integer column)."""


def _check_dataset_name(value: str) -> str:
    try:
        return check_name(value, "dataset name")
    except InvalidName as exc:  # the one name rule (schema/names.py), as for specs and storage
        raise PydanticCustomError("bad_name", str(exc).replace("{", "{{").replace("}", "}}")) from None


NamePath = Annotated[str, Path(description=f"Dataset name (the spec's name): {NAME_RULE.format(n=NAME_MAX)}.",
                               json_schema_extra={"pattern": NAME_PATTERN}),
                     AfterValidator(_check_dataset_name)]
VersionPath = Annotated[str, Path(description=f"Version number 1..{VERSION_MAX} or `latest`.",
                                  json_schema_extra={"pattern": "^(latest|[1-9][0-9]{0,9})$"})]


def parse_version(version: str) -> int | None:
    """``"3"`` -> 3, ``"latest"`` -> None; anything else is a 422 naming the allowed values."""
    if version == "latest":
        return None
    if version.isascii() and version.isdigit() and len(version) <= 10 and 1 <= int(version) <= VERSION_MAX:
        return int(version)
    shown = version if len(version) <= 40 else version[:37] + "..."
    raise RequestValidationError([{
        "type": "version", "loc": ("path", "version"), "input": shown,
        "msg": f"version must be an integer in [1, {VERSION_MAX}] or 'latest'; received {shown!r}",
        "ctx": {"allowed": f"1..{VERSION_MAX} or latest"},
    }])


def _version(store: JobStore, name: str, version: str) -> DatasetVersionRecord:
    number = parse_version(version)
    try:
        return store.get_version(name, number)
    except VersionDeleted:
        raise  # 410 with the tombstone (service.api.errors)
    except VersionNotFound:
        which = "no versions" if number is None else f"no version {number}"
        raise HTTPException(404, f"dataset {name!r} has {which}; list its versions with "
                                 f"GET /v1/datasets/{name}/versions, datasets with GET /v1/datasets") from None


@router.get("", summary="List datasets", response_model=list[DatasetPublic], responses=error_responses(401, 503))
def list_datasets(_token: ReadAuthDep, store: StoreDep) -> list[DatasetPublic]:
    """Every dataset name with its latest version, by name."""
    return [dataset_from_record(d) for d in store.list_datasets()]


@router.get("/{name}/versions", summary="List the versions of a dataset",
            response_model=list[DatasetVersionPublic], responses=error_responses(401, 404, 503))
def list_versions(_token: ReadAuthDep, name: NamePath, store: StoreDep,
                  deleted: Annotated[bool, Query(description="Include the tombstones of deleted versions.")] = False,
                  ) -> list[DatasetVersionPublic]:
    """Versions, oldest first, with their files and checksums."""
    versions = store.list_versions(name, deleted=deleted)
    if not versions:
        raise HTTPException(404, f"no dataset named {name!r}; list datasets with GET /v1/datasets")
    return [DatasetVersionPublic.from_record(v) for v in versions]


@router.get("/{name}/versions/{version}", summary="Read a version: metadata and summary",
            response_model=DatasetVersionDetail, responses=error_responses(401, 404, 410, 422, 503))
def get_version(_token: ReadAuthDep, name: NamePath, version: VersionPath, store: StoreDep) -> DatasetVersionDetail:
    """The version's metadata (spec, seed, photons, shards, code version, timings, checksums) and
    its summary (Rd per estimator, incidence angle, channel and component, with standard errors)."""
    return DatasetVersionDetail.from_record(_version(store, name, version))


@router.api_route(
    "/{name}/versions/{version}/files/{filename}",
    methods=["GET", "HEAD"],
    summary="Download a file of a version",
    response_class=StreamingResponse,
    responses={**DOWNLOAD_RESPONSES, **error_responses(401, 404, 410, 422, 500, 503)},
)
def download_file(_token: ReadAuthDep, request: Request, name: NamePath, version: VersionPath, store: StoreDep,
                  storage: StorageDep,
                  filename: Annotated[str, Path(description="radial.parquet, bins.parquet, summary.parquet, "
                                                             "summary.json or metadata.json")]) -> Response:
    """One of the version's files, verified against the sha256 recorded at publish time; a
    corrupt copy is never served (500). Only the files the version lists exist here. HEAD,
    ``If-None-Match`` (304) and ``Range`` (206) work as for any static file
    (:mod:`service.api.downloads`)."""
    record = _version(store, name, version)
    expected = expected_files(record)
    if filename not in expected:  # only catalogued names: no path ever comes from the request
        raise HTTPException(404, f"{record.name} v{record.version} has no file {shorten(filename)!r}; "
                                 f"available: {', '.join(sorted(expected))}")
    return file_response(request, storage, record, filename, expected[filename],
                         download_name=f"{record.name}-v{record.version}-{filename}")


def _format_problem(fmt: str, message: str) -> RequestValidationError:
    return RequestValidationError([{"type": "export_format", "loc": ("path", "format"), "input": shorten(fmt),
                                    "msg": message, "ctx": {"allowed": ", ".join(FORMATS)}}])


@router.api_route(
    "/{name}/versions/{version}/exports/{format}",
    methods=["GET", "HEAD"],
    summary="Download an export of a version (made once, then stored beside it)",
    response_class=StreamingResponse,
    responses={**DOWNLOAD_RESPONSES, **error_responses(401, 404, 410, 422, 500, 501, 503)},
)
def download_export(_token: ReadAuthDep, request: Request, name: NamePath, version: VersionPath, store: StoreDep,
                    storage: StorageDep,
                    format: Annotated[str, Path(description=f"Export format: {', '.join(FORMATS)}.")]) -> Response:
    """The export as a zip archive: its files and ``export.json`` (dataset, version, spec hash,
    code version, the sha256 of the tables it came from and of every file in it). The first
    request makes it from the version's verified tables and stores it beside the version with
    its sha256 (which is the ETag); later requests serve those bytes, with HEAD, If-None-Match
    and Range as for the version's files. 422 when the dataset cannot be exported in this format
    (the message says what the spec needs), 501 when the server lacks an optional package."""
    record = _version(store, name, version)
    try:
        record, export = ensure_export(store, storage, record.name, record.version, format)
    except UnknownFormat as exc:
        raise _format_problem(format, str(exc)) from None
    except MissingDependency as exc:
        raise HTTPException(501, f"{exc} on the API server") from None
    except ExportError as exc:
        raise _format_problem(format, f"{record.name} v{record.version} cannot be exported as {format}: {exc}") from None
    return file_response(request, storage, record, export.filename, export.sha256,
                         download_name=f"{record.name}-v{record.version}-{format}.zip")


@router.delete("/{name}/versions/{version}", summary="Delete a version", response_model=DatasetVersionPublic,
               responses=error_responses(401, 404, 422, 503))
def delete_version(token: AuthDep, name: NamePath, version: VersionPath, store: StoreDep,
                   storage: StorageDep) -> DatasetVersionPublic:
    """Remove the version's files and keep a tombstone: its row with the spec hash, who deleted
    it and when (GET then answers 410; its number is never reused). Deleting it again returns
    the tombstone. ``latest`` is refused here: name the number you mean to delete."""
    number = parse_version(version)
    if number is None:
        raise RequestValidationError([{
            "type": "version", "loc": ("path", "version"), "input": version,
            "msg": "DELETE needs the version number, not 'latest'; list them with GET "
                   f"/v1/datasets/{name}/versions", "ctx": {"allowed": f"1..{VERSION_MAX}"}}])
    try:
        record = store.delete_version(name, number, token_fingerprint(token))
    except VersionNotFound:
        raise HTTPException(404, f"dataset {name!r} has no version {number}; list its versions with "
                                 f"GET /v1/datasets/{name}/versions") from None
    storage.remove_version(record)
    return DatasetVersionPublic.from_record(record)
