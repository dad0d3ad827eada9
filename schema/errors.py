"""Errors of the spec contract.

Hierarchy::

    ValueError
    ├── SpecError            a spec file or document is invalid (bad JSON, or fails validation);
    │                        the message has one line per problem: dotted field path, what is
    │                        allowed, the value received
    └── ShardIndexError      (also an IndexError) a shard index outside [0, shards)

Pydantic's own ``ValidationError`` (also a ``ValueError``) is what ``SimulationSpec.model_validate``
raises; :func:`schema.load_spec` and :func:`schema.parse_spec` turn it into a ``SpecError``.
"""

from __future__ import annotations

from typing import Any

from pydantic import ValidationError

__all__ = ["SpecError", "ShardIndexError", "format_validation_error"]


class SpecError(ValueError):
    """An invalid simulation spec. ``problems`` holds ``(dotted_path, message)`` pairs."""

    def __init__(self, message: str, problems: list[tuple[str, str]] | None = None):
        super().__init__(message)
        self.problems: list[tuple[str, str]] = problems or []

    @classmethod
    def from_validation_error(cls, err: ValidationError, source: str = "") -> SpecError:
        """Build a readable multi-line error from a pydantic ``ValidationError``; ``source``
        (e.g. the file name) is named in the first line."""
        problems = [(_dotted(e["loc"]), _describe(e)) for e in err.errors()]
        n = len(problems)
        where = f" ({source})" if source else ""
        head = f"invalid simulation spec{where}: {n} problem{'s' if n != 1 else ''}"
        lines = [head] + [f"  {path}: {msg}" for path, msg in problems]
        return cls("\n".join(lines), problems)


class ShardIndexError(IndexError, ValueError):
    """A shard index outside ``[0, shards)``."""


def format_validation_error(err: ValidationError, source: str = "") -> str:
    """The message :class:`SpecError` would carry for ``err``."""
    return str(SpecError.from_validation_error(err, source))


def _dotted(loc: tuple[Any, ...]) -> str:
    return ".".join(str(p) for p in loc) if loc else "(spec)"


def _describe(e: dict[str, Any]) -> str:
    """One error as text; pydantic's built-in messages get the received value appended."""
    msg = e["msg"]
    if e["type"] == "extra_forbidden":
        return f"unknown key {e['loc'][-1]!r} is not allowed here (check the spelling)"
    if e["type"] == "missing":
        return "this field is required"
    if "received" in msg:
        return msg
    value = repr(e.get("input"))
    if len(value) > 80:
        value = value[:77] + "..."
    return f"{msg}; received {value}"
