"""The dataset catalog: published versions (rows are written by ``complete_merge``)."""

from __future__ import annotations

import sqlalchemy as sa

from service.store.base import StoreBase
from service.store.errors import VersionDeleted, VersionNotFound
from service.store.records import DatasetRecord, DatasetVersionRecord
from service.store.tables import dataset_versions

__all__ = ["CatalogMixin"]


class CatalogMixin(StoreBase):
    """Read access to published dataset versions."""

    def list_datasets(self) -> list[DatasetRecord]:
        """Every dataset name with its latest version (deleted versions are not counted), by name."""
        v = dataset_versions.c
        q = (
            sa.select(v.name, sa.func.max(v.version), sa.func.count(), sa.func.max(v.created_at))
            .where(v.deleted_at.is_(None))
            .group_by(v.name)
            .order_by(v.name)
        )
        with self._read() as conn:
            return [DatasetRecord(n, int(latest), int(c), float(t)) for n, latest, c, t in conn.execute(q)]

    def list_versions(self, name: str, *, deleted: bool = False) -> list[DatasetVersionRecord]:
        """Versions of one dataset, oldest first (empty if the name is unknown); tombstones of
        deleted versions too when ``deleted``."""
        q = sa.select(dataset_versions).where(dataset_versions.c.name == name).order_by(dataset_versions.c.version)
        if not deleted:
            q = q.where(dataset_versions.c.deleted_at.is_(None))
        with self._read() as conn:
            return [DatasetVersionRecord.from_row(r) for r in conn.execute(q)]

    def get_version(self, name: str, version: int | None = None) -> DatasetVersionRecord:
        """One version (the latest not deleted if ``version`` is None); raises
        :class:`VersionNotFound`, or :class:`VersionDeleted` (with the tombstone) for a deleted one."""
        q = sa.select(dataset_versions).where(dataset_versions.c.name == name)
        q = q.where(dataset_versions.c.deleted_at.is_(None)).order_by(dataset_versions.c.version.desc()).limit(
            1) if version is None else q.where(dataset_versions.c.version == int(version))
        with self._read() as conn:
            row = conn.execute(q).first()
        if row is None:
            which = "any version" if version is None else f"version {version}"
            raise VersionNotFound(f"dataset {name!r} has no {which}; list them with list_versions({name!r})")
        record = DatasetVersionRecord.from_row(row)
        if record.deleted_at is not None:
            raise VersionDeleted(record)
        return record
