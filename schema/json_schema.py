"""The committed JSON Schema of the spec, ``schema/spec.schema.json``.

Regenerate after changing the spec models with ``python -m schema``; a test checks that
the committed file equals :func:`spec_json_schema_text`.
"""

from __future__ import annotations

import json
from pathlib import Path

from .spec import SimulationSpec

__all__ = ["SPEC_SCHEMA_PATH", "spec_json_schema_text", "write_spec_json_schema"]

SPEC_SCHEMA_PATH = Path(__file__).with_name("spec.schema.json")
"""Where the committed JSON Schema lives (inside the package)."""


def spec_json_schema_text() -> str:
    """``SimulationSpec.model_json_schema()`` as stable text: sorted keys, indent 2, final newline."""
    return json.dumps(SimulationSpec.model_json_schema(), indent=2, sort_keys=True) + "\n"


def write_spec_json_schema(path: Path = SPEC_SCHEMA_PATH) -> Path:
    """Write the JSON Schema to ``path`` and return it."""
    path.write_text(spec_json_schema_text(), encoding="utf-8")
    return path
