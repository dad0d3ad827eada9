"""The plots export (workers.exports.plots): every figure as a valid PNG and SVG, the same bytes
from the same tables, named by estimator, (g, eta) and incidence; an albedo map where a dataset
has several albedos at one (g, eta)."""

from __future__ import annotations

import dataclasses
import json
import xml.etree.ElementTree as ET

import pyarrow as pa
import pyarrow.compute as pc
import pytest

from schema import parse_spec
from tests.workers.conftest import ARRAYS_SPEC

pytest.importorskip("matplotlib", reason="the plots export needs the plot extra (matplotlib), part of the test extra")

from PIL import Image  # noqa: E402  (matplotlib's own dependency)

from workers.exports import MANIFEST, write_export  # noqa: E402


def _only(source, **values):
    """The source with its tables cut to rows whose columns have these values (fewer figures:
    matplotlib takes about a second per file here)."""
    tables = {}
    for name, t in source.tables.items():
        for col, value in values.items():
            t = t.filter(pc.equal(t[col], value))
        tables[name] = t
    return dataclasses.replace(source, tables=tables)


def test_figures_are_valid_and_deterministic(arrays_source, tmp_path):
    first, second = tmp_path / "a", tmp_path / "b"
    first.mkdir()
    second.mkdir()
    names = write_export("plots", _only(arrays_source, estimator="exits", incidence_deg=45.0), first)
    stems = sorted({n.rsplit(".", 1)[0] for n in names if n != MANIFEST})
    # two (g, eta) groups (the channels differ in g), two kinds; no albedo map (one albedo per (g, eta))
    assert stems == sorted(f"{kind}-exits-g{g}-eta1.4000-inc45" for kind in ("rd", "s") for g in ("+0.0000", "+0.7000"))
    again = write_export("plots", _only(arrays_source, estimator="exits", incidence_deg=45.0, channel="R"), second)
    assert set(again) - {MANIFEST} == {f"{k}-exits-g+0.0000-eta1.4000-inc45.{x}" for k in ("rd", "s") for x in ("png", "svg")}
    for stem in stems:
        png, svg = first / f"{stem}.png", first / f"{stem}.svg"
        with Image.open(png) as im:
            assert im.format == "PNG" and im.size[0] > 600 and im.size[1] > 300
        root = ET.parse(svg).getroot()
        assert root.tag.endswith("svg")
        assert b"<dc:date>" not in svg.read_bytes()
        for ext in ("png", "svg"):
            if (second / f"{stem}.{ext}").exists():  # the same tables give the same bytes
                assert (first / f"{stem}.{ext}").read_bytes() == (second / f"{stem}.{ext}").read_bytes(), (stem, ext)
    manifest = json.loads((first / MANIFEST).read_text())
    assert manifest["format"] == "plots" and set(manifest["files"]) == set(names) - {MANIFEST}


def test_albedo_map_figure_when_albedos_share_g_and_eta(arrays_source, tmp_path):
    """The same tables relabelled with one g: two albedos at (g, eta) = (0, 1.4) give a map."""
    same_g = dict(ARRAYS_SPEC, incidence_deg=[0.0], medium=dict(ARRAYS_SPEC["medium"], g=[0.0, 0.0]))
    tables = {}
    for name, t in _only(arrays_source, estimator="exits", incidence_deg=0.0).tables.items():
        i = t.schema.get_field_index("g")
        tables[name] = t.set_column(i, t.schema.field("g"), pa.array([0.0] * t.num_rows))
    source = dataclasses.replace(arrays_source, spec=parse_spec(same_g), tables=tables)
    names = write_export("plots", source, tmp_path)
    assert set(names) == {f"{stem}.{ext}" for stem in ("albedo-map-exits-g+0.0000-eta1.4000",
                                                       "rd-exits-g+0.0000-eta1.4000-inc0", "s-exits-g+0.0000-eta1.4000-inc0")
                          for ext in ("png", "svg")} | {MANIFEST}
