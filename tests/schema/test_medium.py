"""Tests of the spec contract, part 1: the material presets (against the slide table), the
medium forms (preset, explicit, reduced) with their derived quantities, and the validation
messages (field location, allowed range, received value) for every field of a spec.
Bins, sharding, hashing, examples and stored tables are in tests/schema/test_spec.py."""

from __future__ import annotations

import json

import pytest
from pydantic import ValidationError

from schema import (
    PRESETS,
    ChannelOptics,
    MediumSpec,
    SimulationSpec,
    SpecError,
    load_spec,
    parse_spec,
)

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
    ("eta-zero", base(medium={"preset": "skin1", "eta": 0}), "medium.eta", "[0.25, 4]"),
    ("eta-big", base(medium={**MED, "eta": 4.5}), "medium.eta", "[0.25, 4]"),
    ("eta-nan", base(medium={**MED, "eta": float("nan")}), "medium.eta", "[0.25, 4]"),
    ("eta-inf", base(medium={**MED, "eta": float("inf")}), "medium.eta", "[0.25, 4]"),
    ("eta-missing", base(medium={"sigma_a": 0.1, "sigma_s": 1.0}), "medium", "[0.25, 4]"),
    ("g-one", base(medium={**MED, "g": 1.0}), "medium.g", "[-0.999, 0.999]"),
    ("g-list", base(medium={**MED, "sigma_a": [0.1, 0.1], "g": [0.5, -1.0]}), "medium.g",
     "[-0.999, 0.999]"),
    ("sigma_a-neg", base(medium={**MED, "sigma_a": -0.1}), "medium.sigma_a", "[0, 1e6]"),
    ("sigma_s-inf", base(medium={**MED, "sigma_s": float("inf")}), "medium.sigma_s", "[0, 1e6]"),
    ("sigma_s_reduced-nan", base(medium={"sigma_a": 0.1, "sigma_s_reduced": float("nan"),
                                         "eta": 1.3}), "medium.sigma_s_reduced", "[0, 1e6]"),
    ("scale-zero", base(medium={"preset": "skin1", "scale": 0}), "medium.scale", "(0, 1e6]"),
    ("scale-explicit", base(medium={**MED, "scale": 2}), "medium", "scale"),
    ("sigma_t-zero", base(medium={**MED, "sigma_a": [0, 1], "sigma_s": [0, 1]}), "medium",
     "[1e-6, 1e6]"),
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
    ("estimator", base(estimator="mean"), "estimator", "'hybrid', 'exits', 'connections' or 'both'"),
    ("absorption", base(absorption="implicit"), "absorption", "'weights' or 'analog'"),
    ("radial-count-zero", base(bins={"radial": {"count": 0}}), "bins.radial.count", "[1, 4096]"),
    ("radial-count-big", base(bins={"radial": {"count": 4097}}), "bins.radial.count",
     "[1, 4096]"),
    ("radial-max_mm", base(bins={"radial": {"max_mm": 0}}), "bins.radial.max_mm", "[1e-6, 1e6]"),
    ("radial-max_mfp", base(bins={"radial": {"max_mfp": -1}}), "bins.radial.max_mfp",
     "[0.001, 10000]"),
    ("radial-both", base(bins={"radial": {"max_mm": 1, "max_mfp": 1}}), "bins.radial",
     "exactly one of max_mm or max_mfp"),
    ("radial-min_fraction", base(bins={"radial": {"min_fraction": 1.0}}),
     "bins.radial.min_fraction", "[1e-9, 1)"),
    ("radial-spacing", base(bins={"radial": {"spacing": "cubic"}}), "bins.radial.spacing",
     "'linear', 'log' or 'pbrt'"),
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

