"""Serving a stored, checksummed file over HTTP: GET and HEAD, ETag / If-None-Match, Range.

One code path for every download route (dataset files, and exports stored beside a version):

    return file_response(request, storage, record, "radial.parquet", digest, download_name="tiny-v1-radial.parquet")

(``filename`` is relative to the version's directory, so files stored beside a version, such as
exports, take the same path.)

- ``ETag`` is the published sha256 (strong, quoted); ``If-None-Match`` naming it (or ``*``)
  is answered 304 without reading the file: the client's copy has exactly these bytes;
- otherwise the file's sha256 is checked against the published one before a byte is sent, by
  the one checksum check :func:`service.datasets.verified_path` (:class:`ChecksumMismatch` ->
  500 naming the file; a corrupt copy is never served);
- ``Range: bytes=a-b`` / ``a-`` / ``-n`` (one range) -> 206 with ``Content-Range``; a range
  past the end -> 416 with ``Content-Range: bytes */size``; several ranges or a malformed header
  are ignored (200 with the whole file, as RFC 9110 allows), and so is a Range sent with an
  ``If-Range`` that is not the ETag (strong comparison; the files have no Last-Modified, so a
  date never matches): the client's partial copy is of other bytes, it gets the whole file;
- ``Content-Length``, ``Accept-Ranges: bytes`` and ``Content-Disposition`` on every answer;
  HEAD sends the same headers as GET and no body.
"""

from __future__ import annotations

import re
from collections.abc import Iterator

from fastapi import Request
from fastapi.responses import Response, StreamingResponse

from service.datasets import DatasetStorage, verified_path
from service.store import DatasetVersionRecord

__all__ = ["file_response", "parse_range", "etag_matches", "if_range_allows", "MEDIA_TYPES", "DOWNLOAD_RESPONSES"]

_CHUNK = 1 << 20
MEDIA_TYPES = {".parquet": "application/vnd.apache.parquet", ".json": "application/json", ".zip": "application/zip"}
_RANGE = re.compile(r"^bytes=(\d*)-(\d*)$")


def parse_range(header: str | None, size: int) -> tuple[int, int] | None | str:
    """``(start, stop)`` (stop exclusive) of a single byte range, None to send the whole file,
    or ``"unsatisfiable"`` (-> 416). Malformed and multi-range headers are ignored (None)."""
    if not header:
        return None
    m = _RANGE.match(header.strip())
    if m is None:
        return None
    first, last = m.group(1), m.group(2)
    if not first and not last:
        return None
    if not first:  # suffix: the last n bytes
        n = int(last)
        return "unsatisfiable" if n == 0 or size == 0 else (max(0, size - n), size)
    start = int(first)
    stop = size if not last else min(size, int(last) + 1)
    if last and int(last) < start:
        return None  # invalid range: ignored
    return "unsatisfiable" if start >= size else (start, stop)


def etag_matches(header: str | None, etag: str) -> bool:
    """Whether ``If-None-Match`` names ``etag`` (weak comparison, ``*`` matches anything)."""
    if not header:
        return False
    tags = [t.strip() for t in header.split(",")]
    return "*" in tags or any(t.removeprefix("W/") == etag for t in tags)


def if_range_allows(header: str | None, etag: str) -> bool:
    """Whether a Range may be served: no ``If-Range``, or one naming exactly ``etag`` (RFC 9110
    13.1.5: strong comparison, so a weak tag or a date never matches)."""
    return header is None or header.strip() == etag


def _stream(storage: DatasetStorage, path: str, start: int, stop: int) -> Iterator[bytes]:
    with storage.fs.open_input_file(path) as f:
        f.seek(start)
        left = stop - start
        while left > 0:
            chunk = f.read(min(_CHUNK, left))
            if not chunk:
                return
            left -= len(chunk)
            yield chunk


def file_response(request: Request, storage: DatasetStorage, record: DatasetVersionRecord, filename: str,
                  sha256: str, *, download_name: str) -> Response:
    """The answer to GET or HEAD of a version's file ``filename`` published with ``sha256``
    (``download_name`` is offered in Content-Disposition)."""
    etag = f'"{sha256}"'
    suffix = filename[filename.rfind("."):] if "." in filename else ""
    headers = {"ETag": etag, "Accept-Ranges": "bytes", "Cache-Control": "public, max-age=31536000, immutable",
               "Content-Disposition": f'attachment; filename="{download_name}"'}
    if etag_matches(request.headers.get("if-none-match"), etag):
        return Response(status_code=304, headers=headers)
    path = verified_path(storage, record, filename, sha256)  # ChecksumMismatch -> 500
    size = storage.fs.get_file_info(path).size
    media_type = MEDIA_TYPES.get(suffix, "application/octet-stream")
    ranged = if_range_allows(request.headers.get("if-range"), etag)
    wanted = parse_range(request.headers.get("range"), size) if ranged else None
    if wanted == "unsatisfiable":
        return Response(status_code=416, headers={**headers, "Content-Range": f"bytes */{size}"})
    start, stop = wanted if wanted is not None else (0, size)
    status = 206 if wanted is not None else 200
    headers["Content-Length"] = str(stop - start)
    if wanted is not None:
        headers["Content-Range"] = f"bytes {start}-{stop - 1}/{size}"
    if request.method == "HEAD":
        return Response(status_code=status, headers=headers, media_type=media_type)
    return StreamingResponse(_stream(storage, path, start, stop), status_code=status, headers=headers,
                             media_type=media_type)


DOWNLOAD_RESPONSES = {
    200: {"content": {t: {} for t in MEDIA_TYPES.values()},
          "description": "The file, after its sha256 matched the published checksum (also sent as the ETag)."},
    206: {"description": "The byte range asked for with Range: bytes=a-b (Content-Range says which)."},
    304: {"description": "If-None-Match named the ETag: the client's copy is these bytes."},
    416: {"description": "The range starts past the end of the file (Content-Range: bytes */size)."},
}
