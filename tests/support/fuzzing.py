"""The example budget of the fuzz tests (tests/api/test_fuzz.py, tests/schema/test_spec_fuzz.py).

CI runs each with its default count; ``BSSRDF_FUZZ_SCALE=20`` multiplies every count for a longer
hunt by hand (a failure prints the example that reproduces it).
"""

from __future__ import annotations

import os

__all__ = ["examples"]


def examples(default: int) -> int:
    """``default`` x ``BSSRDF_FUZZ_SCALE`` (1 unless set), at least 1."""
    return max(1, round(default * float(os.environ.get("BSSRDF_FUZZ_SCALE", "1"))))
