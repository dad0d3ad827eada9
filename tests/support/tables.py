"""Bitwise comparison of Arrow tables: pyarrow's Table.equals says NaN != NaN, and the tables
hold NaN standard errors where a bin saw no event."""

from __future__ import annotations

import numpy as np
import pyarrow as pa

__all__ = ["bitwise_equal"]


def bitwise_equal(a: pa.Table, b: pa.Table) -> bool:
    """Same schema (names and types), same rows, every value the same bits (NaN equal to NaN)."""
    if a.schema.remove_metadata() != b.schema.remove_metadata() or a.num_rows != b.num_rows:
        return False
    for name in a.column_names:
        x, y = a[name].to_numpy(zero_copy_only=False), b[name].to_numpy(zero_copy_only=False)
        if x.dtype.kind in "fiub":
            if x.tobytes() != y.tobytes():
                return False
        elif not np.array_equal(x, y):
            return False
    return True
