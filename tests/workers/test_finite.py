"""workers.fold.finite: a value column must be finite, a standard error finite or NaN (no error bar)."""

from __future__ import annotations

import math

import pyarrow as pa
import pytest

from schema import SUMMARY_SCHEMA
from workers.fold.finite import NonFiniteResult, check_finite


def _summary(**values) -> pa.Table:
    row = {f.name: 0.0 for f in SUMMARY_SCHEMA} | {"estimator": "exits", "channel": "c0", "component": "total",
                                                  "medium": 7, "photons": 10, "unresolved_bins": 0}
    return pa.Table.from_pylist([row | values], schema=SUMMARY_SCHEMA)


def test_a_nan_standard_error_is_no_error_bar():
    check_finite(_summary(Rd_stderr=math.nan), "summary")


@pytest.mark.parametrize("column, value", [("Rd", math.nan), ("Rd", math.inf), ("absorbed", -math.inf),
                                           ("Rd_stderr", math.inf)])
def test_non_finite_values_are_refused_naming_medium_and_column(column, value):
    with pytest.raises(NonFiniteResult, match=f"medium 7 .*: summary.{column} is {value} in 1 of 1 rows"):
        check_finite(_summary(**{column: value}), "summary")
