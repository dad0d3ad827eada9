"""Reading a simulation spec: from a dict, JSON text or a JSON file, into a validated
:class:`schema.spec.SimulationSpec`, or a :class:`schema.errors.SpecError` that names every bad
field with its allowed range, one line per problem."""

from __future__ import annotations

import json
import os
from typing import Any

from pydantic import ValidationError

from .errors import SpecError
from .spec import SimulationSpec

__all__ = ["parse_spec", "load_spec"]


def parse_spec(data: Any, source: str = "") -> SimulationSpec:
    """Validate a dict (or JSON text/bytes) into a :class:`SimulationSpec`; :class:`SpecError`
    with one line per problem otherwise."""
    try:
        if isinstance(data, (str, bytes, bytearray)):
            return SimulationSpec.model_validate_json(data)
        return SimulationSpec.model_validate(data)
    except ValidationError as err:
        raise SpecError.from_validation_error(err, source) from None


def load_spec(path: str | os.PathLike[str]) -> SimulationSpec:
    """Read and validate a spec JSON file; :class:`SpecError` on bad JSON or bad values."""
    source = os.fspath(path)
    try:
        with open(source, encoding="utf-8") as f:
            data = json.load(f)
    except json.JSONDecodeError as err:
        raise SpecError(f"invalid simulation spec ({source}): not valid JSON: {err}",
                        [("(spec)", str(err))]) from None
    return parse_spec(data, source)
