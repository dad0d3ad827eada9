"""Property-based tests of the spec models (hypothesis): whatever a client sends, validation either
gives a spec everything downstream can use, or a :class:`SpecError` naming each bad field with a
reason; never another exception.

Inputs are valid specs (a single medium, a preset, a sweep, a target) with one to three of their
fields, at any depth, replaced by an arbitrary JSON value (numbers at and past every bound,
NaN and infinities, which Python's JSON parser accepts, huge integers, wrong types, nested
junk), removed, or joined by an unknown key. Budget: EXAMPLES cases (a quarter of it for the last two tests), about 15 s here;
``BSSRDF_FUZZ_SCALE`` multiplies it (tests/support/fuzzing.py).
"""

from __future__ import annotations

import copy
import json
import math

import numpy as np

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from schema import SpecError, parse_spec
from schema.estimate import estimate_shard, job_photons
from tests.support.fuzzing import examples

EXAMPLES = examples(250)

BASES = [
    {"name": "tiny", "medium": {"sigma_a": 1.0, "sigma_s": 1.0, "g": 0.0, "eta": 1.3}, "photons": 200, "shards": 2,
     "batches_per_shard": 1, "seed": 7, "estimator": "exits",
     "bins": {"radial": {"count": 4, "max_mm": 4.0}, "cos_theta_o": {"count": 1}, "phi_o": {"count": 1}}},
    {"name": "rgb", "medium": {"sigma_a": [0.1, 0.2, 0.3], "sigma_s": [9.9, 5.0, 1.0], "g": [0.9, 0.5, 0.0],
                               "eta": 1.5},
     "incidence_deg": [0.0, 45.0], "photons": 1000, "shards": 4,
     "bins": {"radial": {"count": 16, "max_mfp": 16.0, "spacing": "linear"}, "theta_s": {"count": 4}}},
    {"name": "preset", "medium": {"preset": "marble"}, "photons": 2000, "estimator": "both"},
    {"name": "sweep", "sweep": {"albedo": {"count": 3, "spacing": "linear"}, "g": [0.0, 0.9], "eta": [1.3]},
     "photons": 300, "shards": 3, "bins": {"radial": {"spacing": "pbrt", "count": 8}}},
    {"name": "target", "medium": {"sigma_a": 0.5, "sigma_s": 2.0, "g": 0.3, "eta": 1.4}, "photons": 5000,
     "shards": 10, "bins": {"radial": {"count": 4, "max_mm": 2.0, "spacing": "linear"}},
     "target": {"rel_stderr": 0.01, "radial": {"rel_stderr": 0.05, "r_min_mm": 0.0, "r_max_mm": 1.0}}},
]

_bounds = [0, 1, -1, 2, 0.5, -0.0, 1e-300, 0.999999, 1.000001, 90, 89.999, 1024, 1025, 100_000, 100_001,
           2**24, 2**31 - 1, 2**31, 2**40, 2**40 + 1, 2**53 + 1, 2**63 - 1, 2**63, 2**64, 10**30, -(2**63) - 1,
           1e308, -1e308, math.inf, -math.inf, math.nan]
scalars = st.one_of(
    st.none(), st.booleans(), st.sampled_from(_bounds), st.integers(), st.floats(allow_nan=True),
    st.text(max_size=30), st.sampled_from(["", "a" * 2001, "pbrt", "linear", "log", "marble", "both", "\x00", "1e6"]),
)
json_values = st.recursive(scalars, lambda inner: st.one_of(
    st.lists(inner, max_size=5), st.dictionaries(st.text(max_size=10), inner, max_size=4)), max_leaves=12)


def paths(node, prefix=()):
    """Every key path into a nested dict/list document (lists by index)."""
    items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
    for key, value in items:
        yield prefix + (key,)
        yield from paths(value, prefix + (key,))


def mutate(doc, path, action, value):
    """Replace, remove, or add an unknown key beside, the node at ``path`` (a copy is changed)."""
    doc = copy.deepcopy(doc)
    parent = doc
    for key in path[:-1]:
        parent = parent[key]
    last = path[-1]
    if action == "replace":
        parent[last] = value
    elif action == "remove" and isinstance(parent, dict):
        del parent[last]
    elif isinstance(parent, dict):
        parent["unknown_" + str(last)] = value
    return doc


@st.composite
def near_valid_specs(draw):
    doc = draw(st.sampled_from(BASES))
    for _ in range(draw(st.integers(1, 3))):
        candidates = list(paths(doc))
        if not candidates:
            break
        doc = mutate(doc, draw(st.sampled_from(candidates)), draw(st.sampled_from(["replace", "replace", "remove", "add"])),
                     draw(json_values))
    return doc


def field_exists(doc, dotted: str) -> bool:
    """Whether a problem's field names a place in the document (or the document itself): each
    part is a key or index of the input, or one pydantic adds for a union member or a list item."""
    if dotted == "(spec)":
        return True
    node = doc
    for part in dotted.split("."):
        if isinstance(node, dict) and part in node:
            node = node[part]
        elif isinstance(node, list) and part.isdigit() and int(part) < len(node):
            node = node[int(part)]
        else:
            # A missing field (named by its parent's key) or a union branch name such as
            # "list[...]" or "function-after[...]": the prefix so far exists.
            return True
    return True


def check_usable(spec) -> None:
    """What the service and the workers do with an accepted spec, none of which may raise."""
    text = spec.canonical_json()
    again = parse_spec(json.loads(text))
    assert again == spec and again.spec_hash() == spec.spec_hash()  # the stored form is the same spec
    assert spec.task_count() >= 1 and job_photons(spec) >= spec.photons
    estimate = estimate_shard(spec)
    assert math.isfinite(estimate.cpu_s) and estimate.cpu_s >= 0
    for m in range(spec.n_media):
        one = spec.medium_spec(m)
        edges = one.radial_edges_mm()  # per channel when the channels differ in sigma_t
        assert edges.shape[-1] >= 2 and np.isfinite(edges).all() and (np.diff(edges, axis=-1) > 0).all()
    lo, hi = spec.shard_photon_range(spec.shards - 1)
    assert 0 <= lo < hi == spec.photons


@settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.too_slow], database=None)
@given(doc=near_valid_specs())
def test_validation_accepts_a_usable_spec_or_names_every_bad_field(doc):
    try:
        spec = parse_spec(doc)
    except SpecError as exc:
        assert exc.problems, str(exc)
        for field, message in exc.problems:
            assert field and field_exists(doc, field), (field, doc)
            assert len(message) > 10, (field, message)
        return
    check_usable(spec)


@settings(max_examples=EXAMPLES // 4, deadline=None, database=None)
@given(value=json_values)
def test_any_json_document_is_a_spec_error_or_a_spec(value):
    try:
        parse_spec(value)
    except SpecError as exc:
        assert exc.problems


@settings(max_examples=EXAMPLES // 4, deadline=None, database=None)
@given(doc=near_valid_specs())
def test_the_json_text_of_a_document_validates_like_the_document(doc):
    try:
        text = json.dumps(doc)  # NaN and infinities are written as JSON's NaN / Infinity
    except ValueError:
        return
    outcomes = []
    for data in (doc, text):
        try:
            outcomes.append(parse_spec(data).spec_hash())
        except SpecError as exc:
            outcomes.append(sorted(f for f, _ in exc.problems))
    assert isinstance(outcomes[0], str) == isinstance(outcomes[1], str), outcomes
    if isinstance(outcomes[0], str):
        assert outcomes[0] == outcomes[1]
