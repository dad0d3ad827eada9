"""No table holds a non-finite number: the check every table passes before it is written.

A value column (Rd_r, G, S, Rd, ...) must be finite; a standard error may be NaN, which the
tables define as "no error bar" (no event, or S_infinite_variance), but never infinite. Specs
inside the physical ranges of schema.medium and schema.bins give finite tables; this is the
defence behind that validation, so that nothing non-finite is published
(:class:`workers.fold.output.TableWriter`, :func:`workers.fold.job.write_part`).
"""

from __future__ import annotations

import pyarrow as pa
import pyarrow.compute as pc

__all__ = ["NonFiniteResult", "check_finite"]

_WHERE = ("albedo", "g", "eta", "incidence_deg", "channel", "component")


class NonFiniteResult(ValueError):
    """A table would hold NaN or an infinity where a number belongs."""


def check_finite(table: pa.Table, name: str) -> None:
    """Raise :class:`NonFiniteResult` naming the medium, the column and the first bad row if a
    float column of ``table`` (one of radial, bins, summary) is not finite (module docstring)."""
    for field in table.schema:
        if not pa.types.is_floating(field.type) or field.name in _WHERE:
            continue
        column = table.column(field.name)
        bad = pc.is_inf(column) if field.name.endswith("_stderr") else pc.invert(pc.is_finite(column))
        n_bad = pc.sum(bad).as_py() or 0
        if n_bad:
            row = pc.index(bad, True).as_py()
            first = {k: table.column(k)[row].as_py() for k in _WHERE if k in table.schema.names}
            medium = table.column("medium")[row].as_py()
            raise NonFiniteResult(
                f"medium {medium} ({', '.join(f'{k} {v}' for k, v in first.items())}): {name}.{field.name} is "
                f"{column[row].as_py()} in {n_bad} of {len(column)} rows; nothing is published (a medium "
                "outside the physical ranges of schema.medium and schema.bins, or a bug)")
