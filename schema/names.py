"""The one definition of a valid name: datasets (a spec's ``name``) and spectral channels.

A name is 1..``max_length`` characters from ``[A-Za-z0-9._-]`` and starts with a letter or a
digit.  The first character rule keeps every name a plain path segment and a plain command-line
argument: ``.``, ``..`` and ``.hidden`` would be special on a filesystem, ``-rf`` an option.
Datasets allow 100 characters, channels 32.  The spec validation, dataset storage and the HTTP
API all call :func:`check_name` (or read :data:`NAME_PATTERN`), so they cannot disagree.
"""

from __future__ import annotations

import re

__all__ = ["NAME_MAX", "CHANNEL_NAME_MAX", "NAME_PATTERN", "NAME_RULE", "InvalidName", "check_name", "name_pattern"]

NAME_MAX = 100
"""Longest dataset name."""
CHANNEL_NAME_MAX = 32
"""Longest channel name."""

NAME_RULE = "1..{n} characters from [A-Za-z0-9._-], starting with a letter or digit"
"""The rule in words (``{n}`` is the length limit)."""


def name_pattern(max_length: int = NAME_MAX) -> str:
    """The rule as a regular expression (JSON Schema ``pattern``, FastAPI path ``pattern``)."""
    return f"^[A-Za-z0-9][A-Za-z0-9._-]{{0,{max_length - 1}}}$"


NAME_PATTERN = name_pattern(NAME_MAX)
"""The dataset-name rule as a regular expression."""

_COMPILED: dict[int, re.Pattern[str]] = {}


class InvalidName(ValueError):
    """A name that breaks the rule; the message says the rule and shows the value."""


def check_name(name: object, what: str = "name", max_length: int = NAME_MAX) -> str:
    """Return ``name`` if it follows the rule, else raise :class:`InvalidName` naming ``what``."""
    pattern = _COMPILED.get(max_length)
    if pattern is None:
        pattern = _COMPILED[max_length] = re.compile(name_pattern(max_length))
    if not isinstance(name, str) or pattern.fullmatch(name) is None:
        shown = repr(name)
        shown = shown if len(shown) <= 80 else shown[:77] + "..."
        raise InvalidName(f"{what} must be {NAME_RULE.format(n=max_length)}; received {shown}")
    return name
