"""Range checks that explain themselves, as pydantic ``Annotated`` markers.

Pydantic's own ``Field(gt=..., le=...)`` messages say "Input should be greater than 0" but never
show the whole allowed interval, and they let ``inf``/``nan`` through unbounded ranges. Every
numeric field of the spec therefore carries an :class:`Interval`, which

* rejects non-finite numbers (``nan``, ``inf``) whatever the range,
* is strict about the JSON type: ``true`` / ``false`` and strings are refused where a number is
  expected (lax pydantic would read ``"photons": true`` as 1 and ``"g": "0.5"`` as 0.5); an integer
  field still accepts a float with an integral value (``1e6``), as JSON does not tell them apart,
* reports ``"must be in the allowed range (0, 4]; received -1.0"`` (the dotted field path is
  added by pydantic's error location, and by :class:`schema.errors.SpecError`),
* still exports ``minimum`` / ``exclusiveMinimum`` / ``maximum`` / ``exclusiveMaximum`` into the
  JSON Schema.

:class:`PerChannel` does the same for the per-channel coefficient fields of the medium, which
accept a scalar (one channel, or broadcast to all channels) or a list of 1..16 numbers.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Any

from pydantic import GetCoreSchemaHandler, GetJsonSchemaHandler
from pydantic_core import PydanticCustomError, core_schema

__all__ = ["Interval", "PerChannel", "MAX_CHANNELS", "range_error", "refuse_non_number"]

MAX_CHANNELS = 16
"""Most spectral channels a medium may have."""


def range_error(what: str, allowed: str, value: Any) -> PydanticCustomError:
    """A pydantic error whose message names the allowed range and the received value."""
    return PydanticCustomError(
        "out_of_range",
        "{what} must be in the allowed range {allowed}; received {value}",
        {"what": what, "allowed": allowed, "value": _show(value)},
    )


def refuse_non_number(value: Any, what: str = "value") -> Any:
    """Return ``value`` unless it is a boolean or a string, which lax pydantic would coerce to a
    number (``True`` -> 1, ``"5"`` -> 5): a spec that says ``true`` for a count is a mistake."""
    if isinstance(value, (bool, str)):
        kind = "a boolean" if isinstance(value, bool) else "a string"
        raise PydanticCustomError(
            "number_type",
            "{what} must be a JSON number, not {kind}; received {value}",
            {"what": what, "kind": kind, "value": _show(value), "allowed": "a JSON number"},
        )
    return value


def _show(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


@dataclass(frozen=True)
class Interval:
    """Allowed interval for a number: ``lo``/``hi`` bounds (``None`` = unbounded), open or closed.

    Written like ``Interval(0, 4, lo_open=True)`` for (0, 4]. Non-finite values always fail.
    """

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    what: str = "value"

    def __str__(self) -> str:
        lo = "-inf" if self.lo is None else _num(self.lo)
        hi = "inf" if self.hi is None else _num(self.hi)
        left = "(" if self.lo_open or self.lo is None else "["
        right = ")" if self.hi_open or self.hi is None else "]"
        return f"{left}{lo}, {hi}{right}"

    def contains(self, x: float) -> bool:
        """True when ``x`` is finite and inside the interval."""
        if isinstance(x, float) and not math.isfinite(x):
            return False
        if self.lo is not None and (x <= self.lo if self.lo_open else x < self.lo):
            return False
        if self.hi is not None and (x >= self.hi if self.hi_open else x > self.hi):
            return False
        return True

    def check(self, x: Any) -> Any:
        """Return ``x`` unchanged, or raise a pydantic error naming the range and ``x``."""
        if not self.contains(x):
            raise range_error(self.what, str(self), x)
        return x

    def json_bounds(self) -> dict[str, float]:
        """JSON Schema keywords for this interval."""
        out: dict[str, float] = {}
        if self.lo is not None:
            out["exclusiveMinimum" if self.lo_open else "minimum"] = self.lo
        if self.hi is not None:
            out["exclusiveMaximum" if self.hi_open else "maximum"] = self.hi
        return out

    def __get_pydantic_core_schema__(
        self, source: Any, handler: GetCoreSchemaHandler
    ) -> core_schema.CoreSchema:
        inner = handler(source)
        if source in (int, float):
            inner = core_schema.no_info_before_validator_function(
                lambda v: refuse_non_number(v, self.what), inner)
        return core_schema.no_info_after_validator_function(self.check, inner)

    def __get_pydantic_json_schema__(
        self, schema: core_schema.CoreSchema, handler: GetJsonSchemaHandler
    ) -> dict[str, Any]:
        js = handler(schema)
        js.update(self.json_bounds())
        return js


def _num(x: float) -> str:
    """Short form of a bound: 4.0 -> '4', 1e-06 -> '1e-6', 2**40 -> '2**40' for powers of two above 2**20."""
    if isinstance(x, int) and x > 2**20 and (x & (x - 1)) == 0:
        return f"2**{x.bit_length() - 1}"
    if isinstance(x, int) and x > 2**20 and ((x + 1) & x) == 0:
        return f"2**{(x + 1).bit_length() - 1} - 1"
    if isinstance(x, float):
        return re.sub(r"e([+-])0*(\d)", lambda m: f"e{m[1].lstrip('+')}{m[2]}", f"{x:g}")  # 1e+06 -> 1e6
    return str(x)


@dataclass(frozen=True)
class PerChannel:
    """Marker for ``float | list[float]`` coefficient fields: each entry inside ``interval``.

    A list must hold 1..16 entries (:data:`MAX_CHANNELS`); a scalar is one channel or broadcasts.
    Lengths across fields are checked by the medium itself.
    """

    interval: Interval

    def refuse_non_numbers(self, v: Any) -> Any:
        """Booleans and strings are refused (scalar or list entries) before lax coercion."""
        for x in v if isinstance(v, list) else [v]:
            refuse_non_number(x, self.interval.what)
        return v

    def check(self, v: Any) -> Any:
        values = v if isinstance(v, list) else [v]
        if isinstance(v, list) and not 1 <= len(v) <= MAX_CHANNELS:
            raise PydanticCustomError(
                "channel_count",
                "a per-channel list must have between 1 and {n} entries (allowed range "
                "[1, {n}]); received {count} entries",
                {"n": MAX_CHANNELS, "count": len(v)},
            )
        for i, x in enumerate(values):
            if not self.interval.contains(x):
                where = f", channel {i}," if isinstance(v, list) else ""
                raise range_error(f"{self.interval.what}{where}", str(self.interval), x)
        return v

    def __get_pydantic_core_schema__(
        self, source: Any, handler: GetCoreSchemaHandler
    ) -> core_schema.CoreSchema:
        inner = core_schema.no_info_before_validator_function(self.refuse_non_numbers, handler(source))
        return core_schema.no_info_after_validator_function(self.check, inner)

    def __get_pydantic_json_schema__(
        self, schema: core_schema.CoreSchema, handler: GetJsonSchemaHandler
    ) -> dict[str, Any]:
        bounds = self.interval.json_bounds()
        number = {"type": "number", **bounds}
        return {
            "anyOf": [
                number,
                {"type": "array", "items": number, "minItems": 1, "maxItems": MAX_CHANNELS},
            ]
        }
