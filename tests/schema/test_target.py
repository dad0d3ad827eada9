"""The spec's "target" field: accepted forms and the errors for bad ones (field, range, value)."""

from __future__ import annotations

import pytest

from schema import SpecError, parse_spec


def _spec(target) -> dict:
    return {"name": "t", "medium": {"sigma_a": 0.1, "sigma_s": 0.9, "g": 0.0, "eta": 1.0},
            "bins": {"radial": {"count": 4, "max_mm": 2.0, "spacing": "linear"}}, "target": target}  # fmt: skip


def test_default_is_no_target():
    spec = parse_spec({"name": "t", "medium": {"preset": "skin1"}})
    assert spec.target is None


def test_target_forms():
    spec = parse_spec(_spec({"rel_stderr": 0.002}))
    assert spec.target.rel_stderr == 0.002 and spec.target.radial is None
    spec = parse_spec(_spec({"rel_stderr": 0.01, "radial": {"rel_stderr": 0.05, "r_max_mm": 1.0}}))
    assert (spec.target.radial.r_min_mm, spec.target.radial.r_max_mm) == (0.0, 1.0)
    # Part of the spec's identity.
    assert parse_spec(_spec({"rel_stderr": 0.01})).spec_hash() != parse_spec(_spec({"rel_stderr": 0.02})).spec_hash()


@pytest.mark.parametrize(
    "target, field, words",
    [
        ({"rel_stderr": 0.0}, "target.rel_stderr", ["(0, 1)", "0.0"]),
        ({"rel_stderr": 1.5}, "target.rel_stderr", ["(0, 1)", "1.5"]),
        ({"rel_stderr": float("nan")}, "target.rel_stderr", ["(0, 1)"]),
        ({}, "target.rel_stderr", ["required"]),
        ({"rel_stderr": 0.01, "relstderr": 1}, "target.relstderr", ["unknown key"]),
        ({"rel_stderr": 0.01, "radial": {"rel_stderr": 0.1}}, "target.radial.r_max_mm", ["required"]),
        ({"rel_stderr": 0.01, "radial": {"rel_stderr": 0.1, "r_min_mm": 1.0, "r_max_mm": 0.5}}, "target.radial",
         ["r_min_mm must be below r_max_mm", "1.0", "0.5"]),
        ({"rel_stderr": 0.01, "radial": {"rel_stderr": -1, "r_max_mm": 1.0}}, "target.radial.rel_stderr", ["(0, 1)", "-1"]),
        # Edges 0, 0.5, 1, 1.5, 2 mm: [0.6, 0.9] holds no whole bin.
        ({"rel_stderr": 0.01, "radial": {"rel_stderr": 0.1, "r_min_mm": 0.6, "r_max_mm": 0.9}}, "target",
         ["holds no whole radial bin", "0.6", "0.9", "widen"]),
    ],
)
def test_bad_targets_name_field_range_and_value(target, field, words):
    with pytest.raises(SpecError) as err:
        parse_spec(_spec(target))
    paths = [p for p, _ in err.value.problems]
    assert field in paths, (paths, str(err.value))
    msg = dict(err.value.problems)[field]
    for w in words:
        assert w in msg, (w, msg)
