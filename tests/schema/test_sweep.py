"""Tests of sweeps in the spec: the albedo spacings, the grid order and medium index, each
medium's own single-medium spec, the task index <-> (medium, shard) mapping, canonical JSON, and
validation messages naming the field, the allowed range and the value."""

from __future__ import annotations

import json
import math
import random
from decimal import Decimal, getcontext

import numpy as np
import pytest

from schema import ShardIndexError, SimulationSpec, SpecError, parse_spec
from schema.sweep import SweepSpec, linear_albedos, pbrt_albedos, sweep_point, sweep_points


def sweep_spec(**kw) -> dict:
    d = {"name": "s", "sweep": {"albedo": [0.9, 0.5, 0.99], "g": [0.9, 0.0], "eta": [1.5, 1.0]},
         "photons": 1000, "shards": 4, "seed": 7}
    d.update(kw)
    return d


def problems(data) -> list[tuple[str, str]]:
    with pytest.raises(SpecError) as err:
        parse_spec(data)
    return err.value.problems


# ---- albedo spacings ------------------------------------------------------------------------


@pytest.mark.parametrize("n", [2, 3, 10, 100, 1024])
def test_pbrt_spacing_is_pbrts_formula(n):
    getcontext().prec = 40  # the formula in 40 digits, as the reference
    expected = [float((1 - (Decimal(-8) * i / (n - 1)).exp()) / (1 - Decimal(-8).exp())) for i in range(n)]
    got = pbrt_albedos(n)
    np.testing.assert_allclose(got, expected, rtol=3e-16, atol=0)  # a few ulps
    assert got[0] == 0.0 and got[-1] == 1.0  # exact endpoints
    assert all(b > a for a, b in zip(got, got[1:]))
    # pbrt's spacing is dense near 1: the last step is the smallest
    assert n == 2 or got[-1] - got[-2] < got[1] - got[0]


def test_linear_spacing():
    assert linear_albedos(5) == [0.0, 0.25, 0.5, 0.75, 1.0]
    assert linear_albedos(2) == [0.0, 1.0]
    with pytest.raises(ValueError):
        pbrt_albedos(1)


def test_grid_form_resolves_to_values():
    spec = parse_spec(sweep_spec(sweep={"albedo": {"count": 5}, "g": [0.0], "eta": [1.3]}))
    assert spec.sweep.albedo.spacing == "pbrt"  # the default, kept in the canonical form
    assert spec.sweep.albedos() == pbrt_albedos(5)
    lin = parse_spec(sweep_spec(sweep={"albedo": {"count": 3, "spacing": "linear"}, "g": [0.0], "eta": [1.3]}))
    assert [m.albedo for m in lin.media()] == [(0.0,), (0.5,), (1.0,)]


# ---- grid order, coordinates and single-medium specs ----------------------------------------


def test_media_order_albedo_fastest_eta_slowest():
    spec = parse_spec(sweep_spec())
    sw = spec.sweep
    assert sw.albedo == [0.5, 0.9, 0.99] and sw.g == [0.0, 0.9] and sw.eta == [1.0, 1.5]  # sorted
    assert spec.n_media == 12 and spec.is_sweep
    media = spec.media()
    assert [m.index for m in media] == list(range(12))
    for m in media:
        i_a, rest = m.index % 3, m.index // 3
        assert m.albedo == (sw.albedo[i_a],) and m.g == (sw.g[rest % 2],) and m.eta == sw.eta[rest // 2]
        assert sweep_point(sw, m.index) == sweep_points(sw)[m.index]
    with pytest.raises(IndexError):
        sweep_point(sw, 12)


def test_sweep_medium_has_exactly_unit_extinction_and_its_albedo():
    """sigma_a = 1 - albedo, sigma_s = albedo: sigma_t rounds to exactly 1 and sigma_s / sigma_t
    is the coordinate to the last bit, for random albedos and the grid spacings alike."""
    rng = random.Random(3)
    values = [rng.random() for _ in range(20000)] + [rng.random() * 1e-12 for _ in range(1000)]
    values += [1.0 - rng.random() * 1e-12 for _ in range(1000)] + pbrt_albedos(1024) + linear_albedos(999)
    values += [0.0, 1.0, 0.1, 0.3, 0.7, 5e-324, 1.0 - 2**-53]
    for a in values:
        sigma_a, sigma_s = 1.0 - a, a
        assert sigma_a + sigma_s == 1.0, a
        assert sigma_s / (sigma_a + sigma_s) == a
    spec = parse_spec(sweep_spec(sweep={"albedo": {"count": 64}, "g": [0.3], "eta": [1.33]}))
    for m in spec.media():
        (ch,) = m.spec.channels()
        assert ch.sigma_t == 1.0 and ch.albedo == m.albedo[0] and ch.g == m.g[0]


def test_medium_spec_is_the_sweep_spec_with_that_medium():
    spec = parse_spec(sweep_spec(incidence_deg=[30, 0], estimator="both", description="d"))
    m = spec.media()[7]
    single = m.spec
    assert not single.is_sweep and single.n_media == 1 and single.task_count() == 4
    assert single.medium.eta == m.eta and single.medium.g == list(m.g)
    assert single.medium.sigma_s == list(m.albedo) and single.medium.channel_names == ["c0"]
    dumped = spec.model_dump(mode="json")
    for key, value in single.model_dump(mode="json").items():
        if key not in ("medium", "sweep"):
            assert value == dumped[key], key
    assert single == spec.medium_spec(7)
    # A single-medium spec given directly in that form is the same spec (same hash).
    direct = parse_spec({**{k: v for k, v in dumped.items() if k != "sweep"},
                         "medium": {"sigma_a": 1.0 - m.albedo[0], "sigma_s": m.albedo[0], "g": m.g[0], "eta": m.eta}})
    assert direct.spec_hash() == single.spec_hash()


def test_single_medium_job_is_one_medium():
    spec = parse_spec({"name": "t", "medium": {"preset": "skin1"}, "shards": 3})
    (m,) = spec.media()
    assert m.index == 0 and spec.medium_spec(0) is spec and spec.n_media == 1 and not spec.is_sweep
    assert m.albedo == tuple(c.albedo for c in spec.channels()) and m.eta == 1.3
    assert [spec.task_of(t) for t in range(3)] == [(0, 0), (0, 1), (0, 2)]
    with pytest.raises(ShardIndexError, match=r"\[0, 1\)"):
        spec.medium_spec(1)


def test_sweep_has_no_single_channel_list():
    spec = parse_spec(sweep_spec())
    with pytest.raises(ValueError, match="medium_spec"):
        spec.channels()


# ---- tasks ----------------------------------------------------------------------------------


def test_task_index_is_medium_major_with_independent_walks():
    data = sweep_spec()
    data["sweep"] = dict(data["sweep"], walks="independent")
    spec = parse_spec(data)
    assert spec.task_count() == 12 * 4
    pairs = [spec.task_of(t) for t in range(spec.task_count())]
    assert pairs == [(m, s) for m in range(12) for s in range(4)]
    assert all(spec.task_index(m, s) == t for t, (m, s) in enumerate(pairs))
    for bad in (-1, 48, 1.0):
        with pytest.raises(ShardIndexError, match=r"allowed range \[0, 48\)"):
            spec.task_of(bad)
    with pytest.raises(ShardIndexError, match="shard_index"):
        spec.task_index(0, 4)
    with pytest.raises(ShardIndexError, match="walk group index"):
        spec.task_index(12, 0)


def test_task_index_is_walk_group_major_with_shared_walks():
    spec = parse_spec(sweep_spec())  # hybrid, weights: shared walks by default
    groups = spec.walk_groups()
    assert spec.walk_mode() == "shared" and len(groups) < spec.n_media
    assert spec.task_count() == len(groups) * 4
    pairs = [spec.task_of(t) for t in range(spec.task_count())]
    assert pairs == [(k, s) for k in range(len(groups)) for s in range(4)]
    assert all(spec.task_index(k, s) == t for t, (k, s) in enumerate(pairs))


# ---- canonical JSON -------------------------------------------------------------------------


def test_canonical_json_of_equivalent_sweeps_is_equal():
    a = parse_spec(sweep_spec())
    b = parse_spec(sweep_spec(sweep={"albedo": [0.99, 0.5, 0.9], "g": [0.0, 0.9], "eta": [1.0, 1.5]}))
    assert a.spec_hash() == b.spec_hash()
    doc = json.loads(a.canonical_json())
    assert "medium" not in doc and doc["sweep"]["albedo"] == [0.5, 0.9, 0.99]
    assert parse_spec(a.canonical_json()) == a
    grid = parse_spec(sweep_spec(sweep={"albedo": {"count": 4}, "g": [0.0], "eta": [1.0]}))
    assert json.loads(grid.canonical_json())["sweep"]["albedo"] == {"count": 4, "spacing": "pbrt"}
    assert "sweep" not in json.loads(a.medium_spec(0).canonical_json())


def test_bin_limit_counts_one_channel_per_medium():
    bins = {"radial": {"count": 4096}, "theta_s": {"count": 64}, "cos_theta_o": {"count": 64}, "phi_o": {"count": 1}}
    parse_spec(sweep_spec(bins=bins))  # 4096 * 64 * 64 * 1 = 2**24 per medium, 12 media
    too_many = problems(sweep_spec(bins={**bins, "phi_o": {"count": 2}}))
    assert too_many[0][0] == "bins" and "* 2 * 1 * 1 = 33554432" in too_many[0][1]


# ---- validation messages --------------------------------------------------------------------


@pytest.mark.parametrize("sweep, field, needle", [
    ({"albedo": [0.5, 1.5], "g": [0.0], "eta": [1.3]}, "sweep.albedo.list.1", "[0, 1]; received 1.5"),
    ({"albedo": [-0.1], "g": [0.0], "eta": [1.3]}, "sweep.albedo.list.0", "[0, 1]; received -0.1"),
    ({"albedo": [0.5], "g": [1.0], "eta": [1.3]}, "sweep.g.0", "[-0.999, 0.999]; received 1.0"),
    ({"albedo": [0.5], "g": [0.0], "eta": [0.0]}, "sweep.eta.0", "[0.25, 4]; received 0.0"),
    ({"albedo": [0.5], "g": [0.0], "eta": [float("nan")]}, "sweep.eta.0", "[0.25, 4]; received nan"),
    ({"albedo": [0.5, 0.5], "g": [0.0], "eta": [1.3]}, "sweep.albedo", "distinct; received [0.5, 0.5]"),
    ({"albedo": [], "g": [0.0], "eta": [1.3]}, "sweep.albedo", "[1, 1024]); received 0"),
    ({"albedo": [0.5], "g": [], "eta": [1.3]}, "sweep.g", "[1, 64]); received 0"),
    ({"albedo": [0.5], "g": [0.0], "eta": [1 + i / 100 for i in range(65)]}, "sweep.eta", "[1, 64]); received 65"),
    ({"albedo": {"count": 1}, "g": [0.0], "eta": [1.3]}, "sweep.albedo.grid.count", "[2, 1024]; received 1"),
    ({"albedo": {"count": 5, "spacing": "log"}, "g": [0.0], "eta": [1.3]}, "sweep.albedo.grid.spacing", "'log'"),
    ({"albedo": "pbrt", "g": [0.0], "eta": [1.3]}, "sweep.albedo", '{"count": N, "spacing"'),
    ({"albedo": [0.5], "g": [0.0]}, "sweep.eta", "required"),
    ({"albedo": [0.5], "g": [0.0], "eta": [1.3], "sigma_t": 2}, "sweep.sigma_t", "unknown key"),
    ({"albedo": {"count": 1024}, "g": [i / 100 for i in range(64)], "eta": [1.3, 1.4]}, "sweep.eta",
     "[1, 65536]; received 131072 media"),
])
def test_sweep_errors_name_field_range_and_value(sweep, field, needle):
    found = problems(sweep_spec(sweep=sweep))
    assert field in [path for path, _ in found], found
    assert any(needle in msg for path, msg in found if path == field), found


def test_exactly_one_of_medium_and_sweep():
    both = problems(sweep_spec(medium={"preset": "skin1"}))
    assert both == [("(spec)", both[0][1])] and "received medium and sweep" in both[0][1]
    neither = problems({"name": "t"})
    assert "received neither" in neither[0][1]


def test_task_limit():
    found = problems(sweep_spec(sweep={"albedo": {"count": 1000}, "g": [0.0, 0.5], "eta": [1.3]},
                                photons=10**6, shards=501))
    assert found[0][0] == "shards" and "[1, 1000000]; received 1002000 tasks" in found[0][1]


def test_sweep_json_schema_lists_both_forms():
    schema = SimulationSpec.model_json_schema()
    assert {"required": ["sweep"]} in schema["oneOf"] and {"required": ["medium"]} in schema["oneOf"]
    assert "sweep" in schema["properties"]
    assert math.isclose(SweepSpec.model_json_schema()["properties"]["g"]["items"]["maximum"], 0.999)


def test_radial_target_must_hold_a_bin_of_every_medium():
    # max_mfp 16: medium (0.99, 0.9) reaches 16 / (1 - 0.891) = 147 mm, medium (0.1, 0) 16 / 0.9 = 17.8 mm
    sweep = {"albedo": [0.1, 0.99], "g": [0.0, 0.9], "eta": [1.3]}
    target = {"rel_stderr": 0.1, "radial": {"rel_stderr": 0.1, "r_min_mm": 20.0, "r_max_mm": 200.0}}
    found = problems(sweep_spec(sweep=sweep, target=target))
    assert found[0][0] == "target" and "albedo 0.1, g 0" in found[0][1] and "widen it" in found[0][1]
    parse_spec(sweep_spec(sweep=sweep, target={**target, "radial": {**target["radial"], "r_min_mm": 1.0}}))
