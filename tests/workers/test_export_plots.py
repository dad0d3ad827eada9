"""The plots export (workers.exports.plots): every figure as a valid PNG and SVG, the same bytes
from the same tables, named by estimator, (g, eta) and incidence; an albedo map where a dataset
has several albedos at one (g, eta); the Rd figures draw the measured points and both models per
channel, with the models' values."""

from __future__ import annotations

import dataclasses
import json
import math
import xml.etree.ElementTree as ET

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pytest

from schema import parse_spec
from tests.workers.conftest import ARRAYS_SPEC

pytest.importorskip("matplotlib", reason="the plots export needs the plot extra (matplotlib), part of the test extra")

from PIL import Image  # noqa: E402  (matplotlib's own dependency)

from workers.models.diffusion import dipole_rd, pbd_multiple, pbd_rd, pbd_single  # noqa: E402
from workers.exports import MANIFEST, write_export  # noqa: E402
from workers.exports.plots import figures  # noqa: E402


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


def _same_g(arrays_source):
    """The same tables relabelled with one g: both channels' albedos at (g, eta) = (0, 1.4)."""
    same_g = dict(ARRAYS_SPEC, incidence_deg=[0.0], medium=dict(ARRAYS_SPEC["medium"], g=[0.0, 0.0]))
    tables = {}
    for name, t in _only(arrays_source, estimator="exits", incidence_deg=0.0).tables.items():
        i = t.schema.get_field_index("g")
        tables[name] = t.set_column(i, t.schema.field("g"), pa.array([0.0] * t.num_rows))
    return dataclasses.replace(arrays_source, spec=parse_spec(same_g), tables=tables)


def test_albedo_map_figure_when_albedos_share_g_and_eta(arrays_source, tmp_path):
    """The same tables relabelled with one g: two albedos at (g, eta) = (0, 1.4) give a map."""
    source = _same_g(arrays_source)
    names = write_export("plots", source, tmp_path)
    assert set(names) == {f"{stem}.{ext}" for stem in ("albedo-map-exits-g+0.0000-eta1.4000",
                                                       "rd-exits-g+0.0000-eta1.4000-inc0", "s-exits-g+0.0000-eta1.4000-inc0")
                          for ext in ("png", "svg")} | {MANIFEST}


CHANNELS = {"R": dict(sigma_a=0.2, sigma_s=1.8, g=0.0), "G": dict(sigma_a=0.05, sigma_s=0.95, g=0.7)}  # ARRAYS_SPEC
ETA = 1.4
R_SPEC = ((ETA - 1) / (ETA + 1)) ** 2  # Fresnel at normal incidence, independent of workers.walk.optics


def _gids(svg_path) -> set[str]:
    return {el.get("id") for el in ET.parse(svg_path).getroot().iter() if el.get("id")}


def _line(fig, gid):
    (line,) = fig.findobj(match=lambda a: a.get_gid() == gid)  # exactly one artist per curve
    return np.asarray(line.get_xdata(), dtype=float), np.asarray(line.get_ydata(), dtype=float)


def test_rd_figures_draw_the_data_and_both_models_per_channel(arrays_source, tmp_path):
    """At normal incidence every channel's Rd panel holds its measured points and photon beam
    diffusion (every component), and the classical dipole (multiple, total): present in the SVG
    under their ids, and the models' curves equal (1 - R_spec) times workers.models.diffusion's
    profiles for the channel's own coefficients at the plotted radii, from the first to the last
    bin centre (single scattering of channel R resolves one bin only at 400 photons: its models
    are drawn all the same)."""
    source = _only(arrays_source, estimator="exits", incidence_deg=0.0)
    names = write_export("plots", source, tmp_path)
    figs = dict(figures(source))
    rows = source.tables["radial"].filter(pc.equal(source.tables["radial"]["estimator"], "exits")).to_pylist()
    for ch, g in (("R", "+0.0000"), ("G", "+0.7000")):
        stem = f"rd-exits-g{g}-eta1.4000-inc0"
        assert f"{stem}.svg" in names
        ids = _gids(tmp_path / f"{stem}.svg")
        p = CHANNELS[ch]
        for comp in ("single", "multiple", "total"):
            curves = ("measured", "pbd") + (("dipole",) if comp != "single" else ())
            for curve in curves:
                assert f"rd-{curve}-{comp}-m0-{ch}" in ids, (stem, curve, comp)
            assert f"rd-dipole-single-m0-{ch}" not in ids  # the dipole has no single-scattering part
            mine = [r for r in rows if r["channel"] == ch and r["component"] == comp]
            centres = np.array([math.sqrt(r["r_lo_mm"] * r["r_hi_mm"]) if r["r_lo_mm"] > 0 else r["r_hi_mm"] / 2
                                for r in mine])
            keep = np.array([math.isfinite(r["Rd_r_stderr"]) and r["Rd_r"] > 0 for r in mine])
            x, y = _line(figs[stem], f"rd-measured-{comp}-m0-{ch}")
            np.testing.assert_allclose(x, centres[keep], rtol=1e-12)
            np.testing.assert_allclose(y, [r["Rd_r"] for r, k in zip(mine, keep) if k], rtol=1e-12)
            model = {"single": pbd_single, "multiple": pbd_multiple, "total": pbd_rd}[comp]
            x, y = _line(figs[stem], f"rd-pbd-{comp}-m0-{ch}")
            assert x.min() == pytest.approx(centres.min(), rel=1e-12) and x.max() == pytest.approx(centres.max(), rel=1e-12)
            np.testing.assert_allclose(y, (1 - R_SPEC) * model(x, p["sigma_a"], p["sigma_s"], p["g"], ETA), rtol=1e-12)
            assert np.all(y > 0)
            if comp != "single":
                x, y = _line(figs[stem], f"rd-dipole-{comp}-m0-{ch}")
                want = (1 - R_SPEC) * dipole_rd(x, p["sigma_a"], p["sigma_s"] * (1 - p["g"]), ETA)
                np.testing.assert_allclose(y, want, rtol=1e-12)


def test_error_bars_stay_on_the_axes(arrays_source):
    """Every error bar of every Rd figure lies inside its axes' y range (the data have bins whose
    bar reaches 0: those end at the axis bottom), and every drawn point too."""
    clipped = 0
    for stem, fig in figures(_only(arrays_source, estimator="exits")):
        if not stem.startswith("rd-"):
            continue
        for ax in fig.axes:
            lo, hi = ax.get_ylim()
            for coll in ax.collections:
                for seg in coll.get_segments():
                    y = np.asarray(seg)[:, 1]
                    # rd - (rd - bottom) rounds: 1e-4 relative at the bottom of 12 decades
                    assert np.all((y >= lo * (1 - 1e-4)) & (y <= hi * (1 + 1e-9))), (stem, y, lo, hi)
                    clipped += bool(np.isclose(y.min(), lo, rtol=1e-4))
            for line in ax.lines:
                if line.get_gid() and line.get_gid().startswith("rd-measured"):
                    y = np.asarray(line.get_ydata())
                    assert np.all((y >= lo) & (y <= hi)), stem
    assert clipped > 0  # the case that used to run off the axis is exercised


def test_s_rows_share_one_colour_scale(arrays_source):
    """All rows (here two albedos) of the S figure are drawn with the same colour norm."""
    figs = dict(figures(_same_g(arrays_source)))
    fig = figs["s-exits-g+0.0000-eta1.4000-inc0"]
    norms = {(m.norm.vmin, m.norm.vmax) for ax in fig.axes for m in ax.collections if hasattr(m, "get_array")
             and m.get_array() is not None and np.isfinite(np.asarray(m.get_array(), dtype=float)).any()}
    assert len([ax for ax in fig.axes if ax.name == "polar"]) == 8 and len(norms) == 1, norms


def test_albedo_map_band_is_visible_beside_large_model_errors(arrays_source):
    """A measurement 100 times more precise than the models' errors: the +- 2 se band still takes
    a visible share (>= 10 %) of the error panel's height."""
    from workers.exports.albedo_map import COLUMNS, AlbedoMap
    from workers.exports.plots import _albedo_map_figure

    a = np.array([0.3, 0.6, 0.9, 0.99])
    cols = {c: np.full(4, np.nan) for c in COLUMNS}
    cols.update(albedo=a, rho_eff_normal=0.5 * a**2, rho_eff_normal_stderr=np.full(4, 2e-4),
                dipole_rho_eff=0.5 * a**2 + 0.04, dipole_error=np.array([0.01, 0.03, 0.04, -0.02]),
                burley_rho_eff=0.5 * a**2 + 0.08, burley_error=np.array([0.02, 0.05, 0.08, 0.06]))
    fig = _albedo_map_figure(arrays_source, AlbedoMap("exits", 0.0, 1.0, cols))
    right = fig.axes[1]
    (band,) = [c for c in right.collections if "2 standard errors" in str(c.get_label())]
    ys = right.transData.transform(band.get_paths()[0].vertices)[:, 1]
    share = (ys.max() - ys.min()) / right.bbox.height
    print(f"band height / axes height = {share:.3f}")
    assert share >= 0.1
