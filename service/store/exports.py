"""The export catalog: one stored export per (dataset version, format), written once.

A row is inserted after its archive is in storage beside the version
(:mod:`service.datasets.exports`); the unique (version, format) constraint makes the first
writer win when two processes make the same export at once, and the loser reads the winner's
row. A deleted version (a tombstone) has no exports: its directory, archives included, is
removed, and its rows are no longer listed; they go with the row itself (ON DELETE CASCADE).
"""

from __future__ import annotations

from typing import Any

import sqlalchemy as sa
from sqlalchemy.exc import IntegrityError

from service.store.base import StoreBase
from service.store.errors import VersionNotFound
from service.store.records import ExportRecord
from service.store.tables import dataset_exports, dataset_versions

__all__ = ["ExportsMixin"]

_COLUMNS = (dataset_versions.c.name, dataset_versions.c.version, dataset_exports.c.format, dataset_exports.c.filename,
            dataset_exports.c.sha256, dataset_exports.c.bytes, dataset_exports.c.created_at, dataset_exports.c.meta)


def _record(row) -> ExportRecord:
    return ExportRecord(*row)


class ExportsMixin(StoreBase):
    """Catalog of stored exports."""

    def _exports_query(self, name: str, version: int):
        return (sa.select(*_COLUMNS).select_from(dataset_exports.join(dataset_versions,
                                                                      dataset_versions.c.id == dataset_exports.c.version_id))
                .where(dataset_versions.c.name == name, dataset_versions.c.version == int(version),
                       dataset_versions.c.deleted_at.is_(None)))  # a deleted version's exports went with its files

    def get_export(self, name: str, version: int, fmt: str) -> ExportRecord | None:
        """The stored export of version ``version`` of ``name`` in format ``fmt``, or None."""
        with self._read() as conn:
            row = conn.execute(self._exports_query(name, version).where(dataset_exports.c.format == fmt)).first()
        return None if row is None else _record(row)

    def list_exports(self, name: str, version: int) -> list[ExportRecord]:
        """Every stored export of a version, by format."""
        with self._read() as conn:
            rows = conn.execute(self._exports_query(name, version).order_by(dataset_exports.c.format)).all()
        return [_record(r) for r in rows]

    def add_export(self, name: str, version: int, fmt: str, *, filename: str, sha256: str, size: int,
                   meta: dict[str, Any]) -> tuple[ExportRecord, bool]:
        """Record an export whose archive is stored; ``(record, True)``, or the row another
        process recorded first and False. :class:`VersionNotFound` if the version is gone."""
        try:
            with self._tx() as conn:
                version_id = conn.execute(sa.select(dataset_versions.c.id).where(
                    dataset_versions.c.name == name, dataset_versions.c.version == int(version))).scalar_one_or_none()
                if version_id is None:
                    raise VersionNotFound(f"dataset {name!r} has no version {version}")
                conn.execute(sa.insert(dataset_exports).values(
                    version_id=version_id, format=fmt, filename=filename, sha256=sha256, bytes=int(size),
                    created_at=self._now(), meta=meta))
            created = True
        except IntegrityError:
            created = False  # another process recorded this export first: theirs stands
        record = self.get_export(name, version, fmt)
        if record is None:
            raise VersionNotFound(f"dataset {name!r} has no version {version}")
        return record, created
