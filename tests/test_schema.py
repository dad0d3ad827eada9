"""Tests of the spec contract: presets, medium forms, validation messages, bins, sharding, hashing,
examples, the committed JSON Schema and the stored-table schemas."""

from __future__ import annotations

import copy
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
from pydantic import ValidationError

from schema import (
    BINS_SCHEMA,
    COLUMN_DOCS,
    META_RUN,
    META_SCHEMA_VERSION,
    META_SPEC,
    PRESETS,
    RADIAL_SCHEMA,
    SCHEMA_VERSION,
    SPEC_SCHEMA_PATH,
    SUMMARY_SCHEMA,
    BinSpec,
    ChannelOptics,
    MediumSpec,
    ShardIndexError,
    SimulationSpec,
    SpecError,
    load_spec,
    parse_spec,
    spec_json_schema_text,
    table_metadata,
)

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = sorted((ROOT / "examples").glob("*.json"))

# The rows of the "Setting parameters" table (Jensen et al. 2001), copied verbatim from the
# lecture slides: sigma_s' R G B [1/mm], sigma_a R G B [1/mm], diffuse reflectance R G B, eta.
SLIDE_TABLE = """\
Apple	2.29	2.39	1.97	0.0030	0.0034	0.046	0.85	0.84	0.53	1.3
Chicken1	0.15	0.21	0.38	0.015	0.077	0.19	0.31	0.15	0.10	1.3
Chicken2	0.19	0.25	0.32	0.018	0.088	0.20	0.32	0.16	0.10	1.3
Cream	7.38	5.47	3.15	0.0002	0.0028	0.0163	0.98	0.90	0.73	1.3
Ketchup	0.18	0.07	0.03	0.061	0.97	1.45	0.16	0.01	0.00	1.3
Marble	2.19	2.62	3.00	0.0021	0.0041	0.0071	0.83	0.79	0.75	1.5
Potato	0.68	0.70	0.55	0.0024	0.0090	0.12	0.77	0.62	0.21	1.3
Skimmilk	0.70	1.22	1.90	0.0014	0.0025	0.0142	0.81	0.81	0.69	1.3
Skin1	0.74	0.88	1.01	0.032	0.17	0.48	0.44	0.22	0.13	1.3
Skin2	1.09	1.59	1.79	0.013	0.070	0.145	0.63	0.44	0.34	1.3
Spectralon	11.6	20.4	14.9	0.00	0.00	0.00	1.00	1.00	1.00	1.3
Wholemilk	2.55	3.21	3.77	0.0011	0.0024	0.014	0.91	0.88	0.76	1.3
"""


def slide_rows() -> dict[str, tuple[list[float], list[float], float]]:
    rows = {}
    for line in SLIDE_TABLE.splitlines():
        name, *nums = line.split("\t")
        v = [float(x) for x in nums]
        rows[name.lower()] = (v[0:3], v[3:6], v[9])
    return rows


def base(**kw) -> dict:
    """A valid minimal spec dict, with top-level overrides."""
    d = {"name": "t", "medium": {"preset": "skin1"}}
    d.update(kw)
    return d


def explicit(**kw) -> dict:
    m = {"sigma_a": [0.1, 0.2], "sigma_s": [9.9, 5.0], "g": 0.5, "eta": 1.3}
    m.update(kw)
    return base(medium=m)


# ---- presets and medium forms --------------------------------------------------------------


def test_presets_match_the_slide_table():
    rows = slide_rows()
    assert set(PRESETS) == set(rows)
    for name, (s_red, a, eta) in rows.items():
        p = PRESETS[name]
        assert list(p.sigma_s_reduced) == s_red, name
        assert list(p.sigma_a) == a, name
        assert p.eta == eta, name
        s_red_t, a_t, eta_t = p  # a plain tuple too
        assert (list(s_red_t), list(a_t), eta_t) == (s_red, a, eta)


@pytest.mark.parametrize("name", sorted(slide_rows()))
def test_every_preset_resolves_to_the_table(name):
    s_red, a, eta = slide_rows()[name]
    spec = SimulationSpec.model_validate(base(medium={"preset": name.upper()}))
    assert spec.medium.preset == name
    assert spec.medium.eta == eta
    chans = spec.channels()
    assert [c.name for c in chans] == ["R", "G", "B"]
    for c, sr, sa in zip(chans, s_red, a):
        assert c.g == 0.0
        assert c.sigma_a == sa
        assert c.sigma_s == sr  # g = 0: sigma_s = sigma_s'
        assert c.sigma_s_reduced == sr
        assert c.sigma_t > 0


def test_preset_with_g_scale_and_eta_override():
    m = MediumSpec(preset="Marble", g=[0.5, 0.0, -0.5], scale=2.0, eta=1.4)
    assert m.eta == 1.4 and m.scale == 2.0
    for c, sr, sa in zip(m.channels(), PRESETS["marble"].sigma_s_reduced,
                         PRESETS["marble"].sigma_a):
        assert c.sigma_a == pytest.approx(2 * sa)
        assert c.sigma_s == pytest.approx(2 * sr / (1 - c.g))
        assert c.sigma_s_reduced == pytest.approx(2 * sr)


def test_explicit_form_and_derived_quantities():
    spec = SimulationSpec.model_validate(base(medium={
        "sigma_a": 0.1, "sigma_s": 9.9, "g": 0.9, "eta": 1.3}))
    (c,) = spec.channels()
    assert isinstance(c, ChannelOptics)
    assert c.name == "c0"
    assert c.sigma_t == pytest.approx(10.0)
    assert c.albedo == pytest.approx(0.99)
    assert c.sigma_s_reduced == pytest.approx(0.99)
    assert c.sigma_t_reduced == pytest.approx(1.09)
    assert c.transport_mfp_mm == pytest.approx(1 / 1.09)
    with pytest.raises(ValidationError):
        c.sigma_a = 1.0  # frozen


def test_reduced_form_gives_sigma_s():
    m = MediumSpec(sigma_a=[0.01, 0.02, 0.03], sigma_s_reduced=[1.0, 2.0, 3.0],
                   g=[0.9, 0.0, -0.5], eta=0.8, channel_names=["a", "b", "c"])
    chans = m.channels()
    assert [c.name for c in chans] == ["a", "b", "c"]
    assert [c.sigma_s for c in chans] == pytest.approx([10.0, 2.0, 2.0])
    assert [c.sigma_s_reduced for c in chans] == pytest.approx([1.0, 2.0, 3.0])
    assert m.eta == 0.8  # eta < 1 is allowed


def test_scalars_broadcast_and_normalise():
    m = MediumSpec(sigma_a=0.5, sigma_s=[1.0, 2.0, 3.0], eta=1)
    assert m.sigma_a == [0.5, 0.5, 0.5]
    assert m.g == [0.0, 0.0, 0.0]
    assert m.channel_names == ["c0", "c1", "c2"]
    assert m.eta == 1.0


def test_spectralon_has_zero_absorption_but_positive_extinction():
    (r, g, b) = MediumSpec(preset="spectralon").channels()
    assert r.sigma_a == 0.0 and r.albedo == 1.0


# ---- validation messages -------------------------------------------------------------------

MED = {"sigma_a": 0.1, "sigma_s": 1.0, "eta": 1.3}

BAD = [
    # (id, spec dict, dotted location, text the message must contain)
    ("eta-zero", base(medium={"preset": "skin1", "eta": 0}), "medium.eta", "(0, 4]"),
    ("eta-big", base(medium={**MED, "eta": 4.5}), "medium.eta", "(0, 4]"),
    ("eta-nan", base(medium={**MED, "eta": float("nan")}), "medium.eta", "(0, 4]"),
    ("eta-inf", base(medium={**MED, "eta": float("inf")}), "medium.eta", "(0, 4]"),
    ("eta-missing", base(medium={"sigma_a": 0.1, "sigma_s": 1.0}), "medium", "(0, 4]"),
    ("g-one", base(medium={**MED, "g": 1.0}), "medium.g", "(-1, 1)"),
    ("g-list", base(medium={**MED, "sigma_a": [0.1, 0.1], "g": [0.5, -1.0]}), "medium.g",
     "(-1, 1)"),
    ("sigma_a-neg", base(medium={**MED, "sigma_a": -0.1}), "medium.sigma_a", "[0, inf)"),
    ("sigma_s-inf", base(medium={**MED, "sigma_s": float("inf")}), "medium.sigma_s", "[0, inf)"),
    ("sigma_s_reduced-nan", base(medium={"sigma_a": 0.1, "sigma_s_reduced": float("nan"),
                                         "eta": 1.3}), "medium.sigma_s_reduced", "[0, inf)"),
    ("scale-zero", base(medium={"preset": "skin1", "scale": 0}), "medium.scale", "(0, inf)"),
    ("scale-explicit", base(medium={**MED, "scale": 2}), "medium", "scale"),
    ("sigma_t-zero", base(medium={**MED, "sigma_a": [0, 1], "sigma_s": [0, 1]}), "medium",
     "(0, inf)"),
    ("lengths", base(medium={**MED, "sigma_a": [0.1, 0.2, 0.3], "sigma_s": [1, 2]}), "medium",
     "sigma_s has 2 entries, expected 3"),
    ("preset-lengths", base(medium={"preset": "skin1", "g": [0.1, 0.2]}), "medium",
     "g has 2 entries, expected 3"),
    ("too-many-channels", base(medium={**MED, "sigma_a": [0.1] * 17}), "medium.sigma_a",
     "[1, 16]"),
    ("empty-channels", base(medium={**MED, "sigma_s": []}), "medium.sigma_s", "[1, 16]"),
    ("names-length", base(medium={**MED, "channel_names": ["a", "b"]}), "medium",
     "channel_names"),
    ("names-dup", base(medium={**MED, "sigma_a": [1, 1], "channel_names": ["a", "a"]}),
     "medium", "unique"),
    ("both-forms", base(medium={"preset": "skin1", "sigma_a": 0.1}), "medium", "not both"),
    ("sigma_s-and-reduced", base(medium={**MED, "sigma_s_reduced": 1.0}), "medium",
     "exactly one medium form"),
    ("no-form", base(medium={"eta": 1.3}), "medium", "exactly one medium form"),
    ("unknown-preset", base(medium={"preset": "jelly"}), "medium", "skimmilk"),
    ("incidence-90", base(incidence_deg=[0, 90]), "incidence_deg.1", "[0, 90)"),
    ("incidence-neg", base(incidence_deg=[-1]), "incidence_deg.0", "[0, 90)"),
    ("incidence-nan", base(incidence_deg=[float("nan")]), "incidence_deg.0", "[0, 90)"),
    ("incidence-empty", base(incidence_deg=[]), "incidence_deg", "[1, 32]"),
    ("incidence-many", base(incidence_deg=list(range(33))), "incidence_deg", "[1, 32]"),
    ("incidence-dup", base(incidence_deg=[10, 10.0]), "incidence_deg", "distinct"),
    ("photons-zero", base(photons=0), "photons", "[1, 2**40]"),
    ("photons-big", base(photons=2**40 + 1), "photons", "[1, 2**40]"),
    ("seed-neg", base(seed=-1), "seed", "[0, 2**63 - 1]"),
    ("seed-big", base(seed=2**63), "seed", "[0, 2**63 - 1]"),
    ("shards-zero", base(shards=0), "shards", "[1, 100000]"),
    ("shards-big", base(shards=100_001, photons=10**6), "shards", "[1, 100000]"),
    ("shards-gt-photons", base(photons=5, shards=6, batches_per_shard=1), "shards",
     "[1, photons = 5]"),
    ("batches-zero", base(batches_per_shard=0), "batches_per_shard", "[1, 1024]"),
    ("batches-big", base(batches_per_shard=1025), "batches_per_shard", "[1, 1024]"),
    ("batches-one", base(shards=1, batches_per_shard=1), "batches_per_shard",
     "[2, photons = 100000]"),
    ("batches-gt-photons", base(photons=10), "batches_per_shard", "[2, photons = 10]"),
    ("max_scatter-zero", base(max_scatter=0), "max_scatter", "[1, 10000000]"),
    ("name-empty", base(name=""), "name", "1..100 characters"),
    ("name-chars", base(name="a/b"), "name", "[A-Za-z0-9._-]"),
    ("name-long", base(name="x" * 101), "name", "1..100 characters"),
    ("description-long", base(description="x" * 2001), "description", "2000"),
    ("estimator", base(estimator="mean"), "estimator", "'connections', 'exits' or 'both'"),
    ("absorption", base(absorption="implicit"), "absorption", "'weights' or 'analog'"),
    ("radial-count-zero", base(bins={"radial": {"count": 0}}), "bins.radial.count", "[1, 4096]"),
    ("radial-count-big", base(bins={"radial": {"count": 4097}}), "bins.radial.count",
     "[1, 4096]"),
    ("radial-max_mm", base(bins={"radial": {"max_mm": 0}}), "bins.radial.max_mm", "(0, inf)"),
    ("radial-max_mfp", base(bins={"radial": {"max_mfp": -1}}), "bins.radial.max_mfp",
     "(0, inf)"),
    ("radial-both", base(bins={"radial": {"max_mm": 1, "max_mfp": 1}}), "bins.radial",
     "exactly one of max_mm or max_mfp"),
    ("radial-min_fraction", base(bins={"radial": {"min_fraction": 1.0}}),
     "bins.radial.min_fraction", "(0, 1)"),
    ("radial-spacing", base(bins={"radial": {"spacing": "cubic"}}), "bins.radial.spacing",
     "'linear' or 'log'"),
    ("theta_s", base(bins={"theta_s": {"count": 361}}), "bins.theta_s.count", "[1, 360]"),
    ("cos_theta_o", base(bins={"cos_theta_o": {"count": 257}}), "bins.cos_theta_o.count",
     "[1, 256]"),
    ("phi_o", base(bins={"phi_o": {"count": 0}}), "bins.phi_o.count", "[1, 360]"),
    ("total-bins", base(bins={"radial": {"count": 4096}, "theta_s": {"count": 360}}), "bins",
     "2**24 = 16777216"),
    ("unknown-top", base(colour="red"), "colour", "colour"),
    ("unknown-nested", base(medium={"preset": "skin1", "sigma": 1}), "medium.sigma", "sigma"),
    ("unknown-bins", base(bins={"radial": {"cnt": 3}}), "bins.radial.cnt", "cnt"),
    ("name-missing", {"medium": {"preset": "skin1"}}, "name", "required"),
]


@pytest.mark.parametrize("data, loc, text", [b[1:] for b in BAD], ids=[b[0] for b in BAD])
def test_bad_input_names_field_and_range(data, loc, text):
    with pytest.raises(ValidationError) as info:
        SimulationSpec.model_validate(data)
    locs = [".".join(map(str, e["loc"])) for e in info.value.errors()]
    assert loc in locs
    assert text in str(info.value)
    with pytest.raises(SpecError) as info2:
        parse_spec(data, source="x.json")
    err = info2.value
    assert isinstance(err, ValueError)
    msg = str(err)
    assert msg.startswith("invalid simulation spec (x.json)")
    line = next(line for line in msg.splitlines() if line.strip().startswith(loc + ":"))
    assert text in line or text == "required"
    assert (loc, line.split(": ", 1)[1]) in err.problems


def test_spec_error_reports_every_problem_and_the_value(tmp_path):
    p = tmp_path / "bad.json"
    p.write_text(json.dumps(base(photons=-3, medium={"preset": "skin1", "eta": 9})))
    with pytest.raises(SpecError) as info:
        load_spec(p)
    msg = str(info.value)
    assert "2 problems" in msg and str(p) in msg
    assert "medium.eta: " in msg and "received 9" in msg
    assert "photons: " in msg and "received -3" in msg


def test_load_spec_bad_json(tmp_path):
    p = tmp_path / "broken.json"
    p.write_text('{"name": "x", ')
    with pytest.raises(SpecError, match="not valid JSON"):
        load_spec(p)


# ---- bins ----------------------------------------------------------------------------------


def test_radial_edges_linear_fixed_mm():
    spec = SimulationSpec.model_validate(base(bins={"radial": {
        "count": 4, "max_mm": 2.0, "spacing": "linear"}}))
    edges = spec.radial_edges_mm()
    assert edges.dtype == np.float64 and edges.shape == (3, 5)
    for row in edges:
        np.testing.assert_array_equal(row, [0.0, 0.5, 1.0, 1.5, 2.0])


def test_radial_edges_log():
    spec = SimulationSpec.model_validate(base(bins={"radial": {
        "count": 5, "max_mm": 10.0, "min_fraction": 1e-4}}))
    (row, *_) = spec.radial_edges_mm()
    assert row[0] == 0.0 and row[1] == pytest.approx(1e-3) and row[-1] == 10.0
    ratios = row[2:] / row[1:-1]
    np.testing.assert_allclose(ratios, 10.0, rtol=1e-12)  # 1e-3 .. 10 in 4 geometric steps


def test_radial_edges_mfp_per_channel():
    spec = SimulationSpec.model_validate(base(medium={"preset": "skimmilk", "g": 0.5},
                                              bins={"radial": {"count": 48, "max_mfp": 16}}))
    edges = spec.radial_edges_mm()
    assert edges.shape == (3, 49)
    expected = [16.0 / c.sigma_t_reduced for c in spec.channels()]
    np.testing.assert_allclose(edges[:, -1], expected, rtol=1e-15)
    np.testing.assert_allclose(edges[:, 1], 1e-3 * np.array(expected), rtol=1e-12)


def test_radial_default_is_16_mfp_log_48():
    r = BinSpec().radial
    assert (r.count, r.max_mfp, r.max_mm, r.spacing, r.min_fraction) == (48, 16.0, None, "log",
                                                                         1e-3)


@pytest.mark.parametrize("count", [1, 2, 3, 48, 4096])
@pytest.mark.parametrize("spacing", ["linear", "log"])
@pytest.mark.parametrize("min_fraction", [1e-9, 1e-3, 0.999])
def test_radial_edges_strictly_increasing(count, spacing, min_fraction):
    spec = SimulationSpec.model_validate(base(bins={"radial": {
        "count": count, "spacing": spacing, "min_fraction": min_fraction}}))
    edges = spec.radial_edges_mm()
    assert edges.shape == (3, count + 1)
    assert np.all(edges[:, 0] == 0.0)
    assert np.all(np.diff(edges, axis=1) > 0)
    if count == 1:
        np.testing.assert_array_equal(edges[:, 1], 16.0 / np.array(
            [c.sigma_t_reduced for c in spec.channels()]))


def test_theta_s_auto_and_angular_edges():
    normal = SimulationSpec.model_validate(base())
    assert normal.theta_s_count() == 1
    np.testing.assert_array_equal(normal.theta_s_edges(), [0.0, 2 * math.pi])
    oblique = SimulationSpec.model_validate(base(incidence_deg=[45, 0]))
    assert oblique.incidence_deg == [0.0, 45.0]
    assert oblique.theta_s_count() == 12
    assert oblique.theta_s_edges().shape == (13,)
    fixed = SimulationSpec.model_validate(base(bins={"theta_s": {"count": 6},
                                                     "cos_theta_o": {"count": 4},
                                                     "phi_o": {"count": 3}}))
    assert fixed.theta_s_count() == 6
    np.testing.assert_allclose(fixed.theta_s_edges(), np.arange(7) * math.pi / 3)
    np.testing.assert_array_equal(fixed.cos_theta_o_edges(), [0.0, 0.25, 0.5, 0.75, 1.0])
    phi = fixed.phi_o_edges()
    assert phi[0] == 0.0 and phi[-1] == 2 * math.pi and phi.dtype == np.float64


# ---- sharding ------------------------------------------------------------------------------


@pytest.mark.parametrize("photons, shards, batches", [
    (1001, 7, 3), (2, 1, 2), (2, 2, 1), (21, 7, 3), (100_000, 8, 4), (999_983, 97, 13),
    (12345, 100, 1),
])
def test_shards_and_batches_partition_the_photons(photons, shards, batches):
    spec = SimulationSpec.model_validate(base(photons=photons, shards=shards,
                                              batches_per_shard=batches))
    pieces = []
    for i in range(shards):
        start, stop = spec.shard_photon_range(i)
        assert (start, stop) == (i * photons // shards, (i + 1) * photons // shards)
        batches_i = spec.batch_photon_ranges(i)
        assert len(batches_i) == batches
        assert batches_i[0][0] == start and batches_i[-1][1] == stop
        pieces += batches_i
    assert pieces[0][0] == 0 and pieces[-1][1] == photons
    for (a0, b0), (a1, _) in zip(pieces, pieces[1:]):
        assert b0 == a1
    assert all(b > a for a, b in pieces)  # shards * batches <= photons: no empty batch
    assert sum(b - a for a, b in pieces) == photons


def test_huge_photon_counts_split_exactly():
    spec = SimulationSpec.model_validate(base(photons=2**40, shards=100_000,
                                              batches_per_shard=1024))
    assert spec.shard_photon_range(99_999)[1] == 2**40
    assert spec.batch_photon_ranges(99_999)[-1][1] == 2**40


@pytest.mark.parametrize("index", [-1, 8, 100, 1.0])
def test_bad_shard_index(index):
    spec = SimulationSpec.model_validate(base())
    with pytest.raises(ShardIndexError, match=r"\[0, 8\)"):
        spec.shard_photon_range(index)
    with pytest.raises(ValueError):
        spec.batch_photon_ranges(index)
    with pytest.raises(IndexError):
        spec.shard_photon_range(index)


# ---- identity ------------------------------------------------------------------------------


def test_canonical_json_equal_for_equivalent_inputs():
    a = SimulationSpec.model_validate(base(medium={"sigma_a": 0.1, "sigma_s": 1, "eta": 1.3},
                                           incidence_deg=[30, 0]))
    b = SimulationSpec.model_validate_json(json.dumps({
        "incidence_deg": [0.0, 30.0], "medium": {
            "eta": 1.3, "g": [0], "sigma_s": [1.0], "sigma_a": [0.1], "channel_names": ["c0"]},
        "name": "t", "photons": 100_000, "bins": {"radial": {"max_mfp": 16}}}))
    assert a.canonical_json() == b.canonical_json()
    assert a.spec_hash() == b.spec_hash()
    c = SimulationSpec.model_validate(base(medium={"preset": "SKIN1"}))
    d = SimulationSpec.model_validate(base(medium={"preset": "skin1", "eta": 1.3, "scale": 1}))
    assert c.spec_hash() == d.spec_hash()


def test_canonical_json_is_stable_and_round_trips():
    spec = load_spec(ROOT / "examples" / "oblique.json")
    text = spec.canonical_json()
    assert text == spec.canonical_json()
    assert " " not in text.replace("skin1-oblique", "").split('"description"')[0]
    assert json.loads(text) == spec.model_dump(mode="json")
    assert list(json.loads(text)) == sorted(json.loads(text))
    again = SimulationSpec.model_validate_json(text)
    assert again.canonical_json() == text and again == spec
    assert len(spec.spec_hash()) == 64 and int(spec.spec_hash(), 16) >= 0
    assert SimulationSpec.model_validate({**json.loads(text), "seed": 99}).spec_hash() \
        != spec.spec_hash()


def test_spec_is_frozen():
    spec = SimulationSpec.model_validate(base())
    with pytest.raises(ValidationError):
        spec.photons = 5


# ---- examples and JSON Schema --------------------------------------------------------------


def test_examples_exist():
    names = {p.stem for p in EXAMPLES}
    assert {"skimmilk", "marble", "skin1", "oblique", "m1"} <= names


@pytest.mark.parametrize("path", EXAMPLES, ids=[p.stem for p in EXAMPLES])
def test_example_loads(path):
    spec = load_spec(path)
    assert spec.photons * len(spec.channels()) * len(spec.incidence_deg) <= 200_000
    assert spec.shards * spec.batches_per_shard >= 2


def test_m1_example_is_what_it_says():
    (c,) = load_spec(ROOT / "examples" / "m1.json").channels()
    assert (c.sigma_t, c.albedo, c.g) == (pytest.approx(10.0), pytest.approx(0.99), 0.9)


def test_committed_json_schema_is_current():
    assert SPEC_SCHEMA_PATH.read_text(encoding="utf-8") == spec_json_schema_text(), (
        "schema/spec.schema.json is stale: run `python -m schema`")


def test_examples_validate_against_json_schema():
    jsonschema = pytest.importorskip("jsonschema")
    schema = json.loads(SPEC_SCHEMA_PATH.read_text(encoding="utf-8"))
    for path in EXAMPLES:
        jsonschema.validate(json.loads(path.read_text(encoding="utf-8")), schema)
    bad = copy.deepcopy(json.loads(EXAMPLES[0].read_text(encoding="utf-8")))
    bad["photons"] = 0
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(bad, schema)


# ---- stored tables -------------------------------------------------------------------------


def test_table_schemas():
    keys = ["estimator", "incidence_deg", "channel", "component"]
    assert RADIAL_SCHEMA.names == keys + ["r_lo_mm", "r_hi_mm", "Rd_r", "Rd_r_stderr"]
    assert BINS_SCHEMA.names == keys + [
        "r_lo_mm", "r_hi_mm", "theta_s_lo", "theta_s_hi", "cos_theta_o_lo", "cos_theta_o_hi",
        "phi_o_lo", "phi_o_hi", "G", "G_stderr", "S", "S_stderr"]
    assert SUMMARY_SCHEMA.names == keys + [
        "R_spec", "Rd", "Rd_stderr", "Rd_beyond_rmax", "Rd_beyond_rmax_stderr", "absorbed",
        "absorbed_stderr", "truncated", "truncated_stderr", "photons"]
    for schema in (RADIAL_SCHEMA, BINS_SCHEMA, SUMMARY_SCHEMA):
        for f in schema:
            assert f.name in COLUMN_DOCS
            if f.name in ("estimator", "channel", "component"):
                assert f.type == pa.string()
            elif f.name == "photons":
                assert f.type == pa.int64()
            else:
                assert f.type == pa.float64()
    table = pa.Table.from_pylist([{
        "estimator": "exits", "incidence_deg": 0.0, "channel": "R", "component": "total",
        "r_lo_mm": 0.0, "r_hi_mm": 1.0, "Rd_r": 0.5, "Rd_r_stderr": 0.01}], schema=RADIAL_SCHEMA)
    md = table_metadata('{"a":1}', {"photons": 3})
    table = table.replace_schema_metadata(md)
    assert table.schema.metadata[META_SCHEMA_VERSION] == SCHEMA_VERSION.encode()
    assert json.loads(table.schema.metadata[META_RUN]) == {"photons": 3}
    assert table.schema.metadata[META_SPEC] == b'{"a":1}'


def test_schema_package_imports_no_torch_or_fastapi():
    code = ("import sys, schema; bad = {'torch', 'fastapi'} & set(sys.modules); "
            "assert not bad, bad")
    subprocess.run([sys.executable, "-c", code], cwd=ROOT, check=True)
