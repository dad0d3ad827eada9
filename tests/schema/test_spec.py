"""Tests of the spec contract, part 2: bin edges, sharding into photon ranges, canonical JSON and
hashing, the examples, the committed JSON Schema and the stored-table schemas.
Presets, medium forms and validation messages are in tests/schema/test_medium.py."""

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
    RADIAL_SCHEMA,
    SCHEMA_VERSION,
    SPEC_SCHEMA_PATH,
    SUMMARY_SCHEMA,
    BinSpec,
    ShardIndexError,
    SimulationSpec,
    SpecError,
    load_spec,
    parse_spec,
    pbrt_radius_nodes,
    spec_json_schema_text,
    table_metadata,
)

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = sorted((ROOT / "examples").glob("*.json"))


def base(**kw) -> dict:
    """A valid minimal spec dict, with top-level overrides."""
    d = {"name": "t", "medium": {"preset": "skin1"}}
    d.update(kw)
    return d



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


def test_radial_edges_pbrt_are_centred_on_pbrts_nodes_per_channel():
    spec = SimulationSpec.model_validate(base(bins={"radial": {"count": 64, "spacing": "pbrt"}}))
    r = spec.bins.radial
    assert (r.max_mm, r.max_mfp) == (None, None)  # the nodes fix the extent
    nodes = pbrt_radius_nodes(64)
    # pbrt-v3 ComputeBeamDiffusionBSSRDF: r[0] = 0, r[1] = 2.5e-3, r[i] = 1.2 r[i-1].
    expected = [0.0, 2.5e-3]
    for _ in range(62):
        expected.append(expected[-1] * 1.2)
    np.testing.assert_allclose(nodes, expected, rtol=1e-13)
    assert nodes[-1] == pytest.approx(202.85, rel=1e-4)
    edges = spec.radial_edges_mm()
    assert edges.shape == (3, 65)
    for row, c in zip(edges, spec.channels()):
        optical = row * c.sigma_t
        assert optical[0] == 0.0 and np.all(np.diff(optical) > 0)
        # bins 1.. are centred on the nodes in log r (geometric midpoint of the edges)
        np.testing.assert_allclose(np.sqrt(optical[1:-1] * optical[2:]), nodes[1:], rtol=1e-13)
        assert optical[1] == pytest.approx(2.5e-3 / math.sqrt(1.2), rel=1e-14)


@pytest.mark.parametrize("radial, field", [
    ({"count": 64, "spacing": "pbrt", "max_mm": 3.0}, "bins.radial"),
    ({"count": 64, "spacing": "pbrt", "max_mfp": 16}, "bins.radial"),
    ({"count": 1, "spacing": "pbrt"}, "bins.radial"),
])
def test_radial_pbrt_refuses_an_extent_or_one_node(radial, field):
    with pytest.raises(SpecError) as info:
        parse_spec(base(bins={"radial": radial}))
    assert field in str(info.value)
    assert "pbrt" in str(info.value) and "received" in str(info.value)


def test_theta_s_auto_and_angular_edges():
    normal = SimulationSpec.model_validate(base())
    assert normal.theta_s_count() == 1
    np.testing.assert_array_equal(normal.theta_s_edges(), [-math.pi, math.pi])  # one bin, centred on +x
    oblique = SimulationSpec.model_validate(base(incidence_deg=[45, 0]))
    assert oblique.incidence_deg == [0.0, 45.0]
    assert oblique.theta_s_count() == 12
    assert oblique.theta_s_edges().shape == (13,)
    fixed = SimulationSpec.model_validate(base(bins={"theta_s": {"count": 6},
                                                     "cos_theta_o": {"count": 4},
                                                     "phi_o": {"count": 3}}))
    assert fixed.theta_s_count() == 6
    # Centred on +x: bin k = [(k - 1/2) h, (k + 1/2) h), h = 2 pi / 6.
    np.testing.assert_allclose(fixed.theta_s_edges(), (np.arange(7) - 0.5) * math.pi / 3, rtol=1e-15, atol=1e-15)
    np.testing.assert_array_equal(fixed.cos_theta_o_edges(), [0.0, 0.25, 0.5, 0.75, 1.0])
    phi = fixed.phi_o_edges()
    # Centred on the outward radial direction: bin 0 = [-pi/3, pi/3) holds phi_o = 0.
    assert phi[0] == -math.pi / 3 and phi[1] == pytest.approx(math.pi / 3, rel=1e-15) and phi.dtype == np.float64
    assert phi[-1] == pytest.approx(2 * math.pi - math.pi / 3, rel=1e-15)


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
    # the form not given ("sweep" here), an absent target, path_roulette and stretch are left
    # out, so single-medium hashes did not change
    left_out = ("sweep", "target", "path_roulette", "stretch")
    assert json.loads(text) == {k: v for k, v in spec.model_dump(mode="json").items() if k not in left_out}
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
    channels = sum(len(m.albedo) for m in spec.media())  # every channel of every medium (sweeps too)
    assert spec.photons * channels * len(spec.incidence_deg) <= 200_000
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
    keys = ["estimator", "medium", "albedo", "g", "eta", "incidence_deg", "channel", "component"]
    assert RADIAL_SCHEMA.names == keys + ["r_lo_mm", "r_hi_mm", "Rd_r", "Rd_r_stderr", "events"]
    assert BINS_SCHEMA.names == keys + [
        "r_lo_mm", "r_hi_mm", "theta_s_lo", "theta_s_hi", "cos_theta_o_lo", "cos_theta_o_hi",
        "phi_o_lo", "phi_o_hi", "G", "G_stderr", "S", "S_stderr", "S_infinite_variance", "events"]
    assert SUMMARY_SCHEMA.names == keys + [
        "R_spec", "Rd", "Rd_stderr", "Rd_beyond_rmax", "Rd_beyond_rmax_stderr", "absorbed",
        "absorbed_stderr", "truncated", "truncated_stderr", "photons", "unresolved_bins"]
    for schema in (RADIAL_SCHEMA, BINS_SCHEMA, SUMMARY_SCHEMA):
        for f in schema:
            assert f.name in COLUMN_DOCS
            if f.name in ("estimator", "channel", "component"):
                assert f.type == pa.string()
            elif f.name in ("photons", "medium", "events", "unresolved_bins", "S_infinite_variance"):
                assert f.type == pa.int64()
            else:
                assert f.type == pa.float64()
    table = pa.Table.from_pylist([{
        "estimator": "exits", "medium": 0, "albedo": 0.9, "g": 0.0, "eta": 1.3, "incidence_deg": 0.0,
        "channel": "R", "component": "total", "r_lo_mm": 0.0, "r_hi_mm": 1.0, "Rd_r": 0.5, "Rd_r_stderr": 0.01,
        "events": 12}], schema=RADIAL_SCHEMA)
    md = table_metadata('{"a":1}', {"photons": 3})
    table = table.replace_schema_metadata(md)
    assert table.schema.metadata[META_SCHEMA_VERSION] == SCHEMA_VERSION.encode()
    assert json.loads(table.schema.metadata[META_RUN]) == {"photons": 3}
    assert table.schema.metadata[META_SPEC] == b'{"a":1}'


def test_schema_package_imports_no_torch_or_fastapi():
    code = ("import sys, schema; bad = {'torch', 'fastapi'} & set(sys.modules); "
            "assert not bad, bad")
    subprocess.run([sys.executable, "-c", code], cwd=ROOT, check=True)


def test_the_production_table_spec_asks_for_the_renderers_table():
    """docs/pbrt-table.json (README, "Far tails at low albedo"): pbrt's 99 non-zero albedos x 64
    nodes at g 0, eta 1.33, 0.2 % on Rd and 1 % in every radial bin from 0.001 mfp up to and
    including the bin of the node at 9.14 mfp, with roulette and stretching."""
    from schema.bins import pbrt_radius_nodes
    from schema.sweep import pbrt_albedos

    spec = load_spec(ROOT / "docs" / "pbrt-table.json")
    assert spec.sweep.albedos() == [a for a in pbrt_albedos(100) if a > 0]
    assert (spec.sweep.g, spec.sweep.eta, spec.bins.radial.count) == ([0.0], [1.33], 64)
    assert spec.target.rel_stderr == 0.002 and spec.target.radial.rel_stderr == 0.01
    edges = spec.medium_spec(0).radial_edges_mm()[0]  # mm = mean free paths (sigma_t = 1/mm)
    nodes = pbrt_radius_nodes(64)
    checked = [j for j in range(64) if edges[j] >= spec.target.radial.r_min_mm and edges[j + 1] <= spec.target.radial.r_max_mm]
    assert [nodes[j] for j in checked] == [r for r in nodes if 0.001 <= r <= 10.0]
    assert spec.stretch is not None and spec.path_roulette is not None
