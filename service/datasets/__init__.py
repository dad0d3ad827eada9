"""Immutable, versioned datasets on a pyarrow filesystem, catalogued in the job store.

    storage = DatasetStorage(".bssrdf/data")               # or file://..., s3://bucket/prefix
    v = open_version(store, storage, "skimmilk", 2)        # verifies every sha256
    v.read_table("radial.parquet")

Modules: :mod:`.storage` (layout, staging, atomic publish, verified reads), :mod:`.metadata`
(metadata.json, code version), :mod:`.jobfiles` (a job's staging area: shard results, folds,
parts), :mod:`.publish` (the merge task run by workers: an incremental fold), :mod:`.exports`
(exports made once and stored beside a version; imported by name, it pulls in workers.exports).
"""

from service.datasets.jobfiles import JobFiles
from service.datasets.metadata import build_metadata
from service.datasets.publish import IncompleteShards, ResultWindow, run_merge_task
from service.datasets.storage import (
    METADATA_FILE,
    DatasetStorage,
    OpenVersion,
    StagedVersion,
    expected_files,
    open_version,
    verified_bytes,
    verified_path,
    sha256_file,
)

__all__ = [
    "DatasetStorage",
    "StagedVersion",
    "OpenVersion",
    "open_version",
    "expected_files",
    "verified_path",
    "verified_bytes",
    "sha256_file",
    "JobFiles",
    "METADATA_FILE",
    "run_merge_task",
    "ResultWindow",
    "IncompleteShards",
    "build_metadata",
]
